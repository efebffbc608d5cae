"""The Prefect automations a lab that recalibrates unattended wants, as code that creates
them on its server (``tcspc flow automations --create``):

- **campaign refused**: a ``tcspc.calibration.refused`` event (the candidate was not
  published; the event's payload says by which rule and why);
- **campaign crashed**: a campaign's flow run Crashed, Failed or TimedOut (Prefect's own
  ``prefect.flow-run.<state name>`` events, about the flow ``calibration_campaign``);
- **calibration stale**: no ``tcspc.calibration.published`` event for ``stale_h`` hours
  (a Proactive trigger, one per calibration directory: the nightly runs refuse, or no
  longer run).

Each notifies through a notification block (``notify``: its block document id) or, without
one, does nothing but fire (the UI's Automations and Events pages show each firing, and
``prefect.automation.triggered`` events are there to build on). Created again with the same
name, an automation is replaced, not duplicated.
"""

from __future__ import annotations

from datetime import timedelta
from uuid import UUID

#: the campaign flow's name (what the crashed trigger matches on its runs' events)
CAMPAIGN_FLOW = "calibration_campaign"
#: a night without a publish is normal (a refusal keeps a good calibration); this long
#: without one is not
STALE_H = 7 * 24.0 + 12


def _resource(out: str | None) -> str:
    """The ``tcspc.calibration.*`` events' resource id for ``out`` (None: any)."""
    if out is None:
        return "tcspc.calibration.*"
    from flows.calibration import _slug

    return f"tcspc.calibration.{_slug(out)}"


def lab_automations(out: str | None = None, stale_h: float = STALE_H,
                    notify: UUID | None = None) -> list:
    """The three automations (not yet created): on every calibration directory, or on
    ``out`` only (its name in theirs)."""
    from prefect.automations import Automation, DoNothing, EventTrigger, Posture, SendNotification

    where = "" if out is None else f" ({_resource(out).removeprefix('tcspc.calibration.')})"
    rid = _resource(out)

    def act(subject: str, body: str) -> list:
        if notify is None:
            return [DoNothing()]
        return [SendNotification(block_document_id=notify, subject=subject, body=body)]

    return [
        Automation(
            name=f"tcspc campaign refused{where}",
            description="A calibration campaign refused its candidate: the current "
                        "calibration stays; the event says by which rule and why.",
            trigger=EventTrigger(expect={"tcspc.calibration.refused"},
                                 match={"prefect.resource.id": rid},
                                 posture=Posture.Reactive, threshold=1),
            actions=act("Calibration refused: {{ event.resource['prefect.resource.name'] }}",
                        "Rule {{ event.payload.rule }}: {{ event.payload.why }}")),
        Automation(
            name=f"tcspc campaign crashed{where}",
            description="A calibration campaign's run Crashed, Failed or TimedOut: nothing "
                        "was published; look at its logs.",
            trigger=EventTrigger(expect={"prefect.flow-run.Crashed", "prefect.flow-run.Failed",
                                         "prefect.flow-run.TimedOut"},
                                 match={"prefect.resource.id": "prefect.flow-run.*"},
                                 match_related={"prefect.resource.role": "flow",
                                                "prefect.resource.name": CAMPAIGN_FLOW},
                                 posture=Posture.Reactive, threshold=1),
            actions=act("Calibration campaign {{ flow_run.name }}: {{ flow_run.state.name }}",
                        "{{ flow_run.state.message }}")),
        Automation(
            name=f"tcspc calibration stale{where}",
            description=f"No calibration published for {stale_h:g} hours: the chip drifts "
                        "on a calibration that grows old.",
            trigger=EventTrigger(expect={"tcspc.calibration.published"},
                                 match={"prefect.resource.id": rid},
                                 for_each={"prefect.resource.id"},
                                 posture=Posture.Proactive, threshold=1,
                                 within=timedelta(hours=stale_h)),
            actions=act("Calibration stale",
                        f"No calibration published for {stale_h:g} hours.")),
    ]


def create(automations: list) -> list[tuple[str, UUID]]:
    """Create ``automations`` on the server (PREFECT_API_URL), each replacing any of the
    same name. Returns (name, id) of each."""
    from prefect import get_client

    made = []
    with get_client(sync_client=True) as client:
        for a in automations:
            for old in client.read_automations_by_name(a.name):
                client.delete_automation(old.id)
            made.append((a.name, a.create().id))
    return made
