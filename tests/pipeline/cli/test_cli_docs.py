"""docs/cli.md is written from the click commands (`make docs`); it must not drift."""

from pathlib import Path

from pipeline.cli.docs import cli_markdown

DOCS = Path(__file__).parents[3] / "docs" / "cli.md"


def test_cli_reference_does_not_drift():
    assert DOCS.read_text() == cli_markdown(), "docs/cli.md is stale: run `make docs`"


def test_cli_reference_covers_every_command():
    text = cli_markdown()
    for cmd in ("tcspc calibrate delay", "tcspc range", "tcspc stage sink", "tcspc flow run",
                "tcspc model predict", "tcspc daemon"):
        assert f"`{cmd}`" in text


def test_topology_keys_do_not_drift():
    """docs/operations.md's table of every topology key is the schema's (`make docs`)."""
    from pipeline.cli.docs import topology_markdown, with_topology
    from pipeline.stream.topology import SECTIONS

    page = (Path(__file__).parents[3] / "docs" / "operations.md").read_text()
    assert with_topology(page) == page, "docs/operations.md's topology keys are stale: " \
                                        "run `make docs`"
    table = topology_markdown()
    for sec, model in SECTIONS.items():
        assert f"`[{sec}]`" in table
        for key, info in model.model_fields.items():
            assert f"| `{key}` |" in table and info.description, (sec, key)
