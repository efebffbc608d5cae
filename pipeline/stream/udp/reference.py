"""The run's reference: which stream is the run's, never whichever datagram came first."""

from __future__ import annotations

from pipeline.stream import datagram
from pipeline.stream.udp.order import _signed32, consistent

QUORUM = 3                     #: datagrams that must agree before they set the reference
QUORUM_HOLD = 256              #: candidates held while no quorum is reached


class Reference:
    """The run's reference (its gate, TDC count, and where sequence numbers and cycles
    stand), never taken from whichever datagram comes first: from the configuration
    (``gate_ps``, ``n_tdc``, ``first_seq``: the run's first datagram is ``first_seq`` at
    cycle 0), from the journal of the run a restarted ingest resumes (``anchor``: the newest
    journaled datagram's sequence number and first cycle), or from a quorum: ``quorum``
    datagrams with the same gate and TDC count whose sequence numbers and cycles could
    belong to one stream (:func:`consistent`), and that agree with the configuration and the
    anchor. Until then datagrams are held (at most QUORUM_HOLD: beyond, the oldest is a
    stray); when the quorum forms, the held datagrams that agree with it are taken in their
    arrival order, the others are strays (counted, quarantined).

    Datagrams agree only when they come from the same sender (``addr``): a quorum is one
    sender's stream, never three senders' datagrams that happen to fit; ``sender`` is
    the one whose quorum fixed the reference."""

    def __init__(self, quorum: int = QUORUM, n_tdc: int | None = None,
                 gate_ps: int | None = None, anchor: tuple[int, int] | None = None):
        self.quorum, self.n_tdc, self.gate_ps, self.anchor = quorum, n_tdc, gate_ps, anchor
        self.held: list[tuple[datagram.Datagram, bytes, tuple | None]] = []
        self.sender: tuple | None = None

    def _fits(self, d: datagram.Datagram) -> bool:
        if (self.n_tdc is not None and d.n_tdc != self.n_tdc) or (
                self.gate_ps is not None and d.t_laser_win_ps != self.gate_ps):
            return False
        if self.anchor is None:
            return True
        seq, cycle = self.anchor
        return consistent(_signed32(d.seq - seq), d.first_cycle - cycle, d.n_tdc)

    @staticmethod
    def agree(a: datagram.Datagram, b: datagram.Datagram) -> bool:
        return (a.n_tdc == b.n_tdc and a.t_laser_win_ps == b.t_laser_win_ps
                and consistent(_signed32(b.seq - a.seq), b.first_cycle - a.first_cycle,
                               a.n_tdc))

    def _with(self, c: tuple, o: tuple) -> bool:
        return c[2] == o[2] and self.agree(c[0], o[0])

    def offer(self, d: datagram.Datagram, data: bytes, addr: tuple | None = None
              ) -> tuple[list | None, list]:
        """Hold ``d``: ``(taken, strays)``, ``taken`` None while no quorum has formed, else
        the held datagrams (``(d, data, addr)``) that agree with it, in arrival order."""
        strays = []
        c = (d, data, addr)
        if not self._fits(d):
            return None, [c]
        self.held.append(c)
        # distinct datagrams: a stray sent three times is not a quorum
        group = {o[0].seq for o in self.held if self._with(c, o)}
        if len(group) >= self.quorum:
            return self._fix(c)
        if len(self.held) > QUORUM_HOLD:
            strays.append(self.held.pop(0))
        return None, strays

    def settle(self) -> tuple[list, list]:
        """The stream's end without a quorum: the largest group that agrees (the earliest of
        equals) is the run's; the rest are strays."""
        if not self.held:
            return [], []
        best = max(self.held, key=lambda c: len({o[0].seq for o in self.held
                                                  if self._with(c, o)}))
        return self._fix(best)

    def _fix(self, c: tuple) -> tuple[list, list]:
        taken = [o for o in self.held if self._with(c, o)]
        strays = [o for o in self.held if not self._with(c, o)]
        self.held = []
        self.n_tdc, self.gate_ps, self.sender = c[0].n_tdc, c[0].t_laser_win_ps, c[2]
        return taken, strays
