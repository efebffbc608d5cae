"""Where a restarted ingest takes the run up: the journal's index of its datagrams."""

from __future__ import annotations

from pathlib import Path


def resume_state(journal: str | Path, run: str) -> dict | None:
    """Where a restarted ingest takes the run up (from the journal's index: each chunk, a
    batch of consecutive datagrams, records their unwrapped sequence numbers: ``seq`` the
    highest, ``seq_cycle`` its first cycle, ``seq_lo`` the lowest, ``datagrams`` how many;
    a chunk of one datagram, as an ingest before batches wrote them, has ``seq`` alone), or
    None for a run not yet journaled by a
    UDP ingest: ``next_cycle`` (the end of the journaled stream), ``seq_lo``/``seq_hi``,
    ``taken`` (datagrams journaled), ``late`` (datagrams that came too late, counted by the
    ingest that journaled the last chunk), ``anchor`` (the newest datagram's sequence number
    and first cycle), ``gap_cycles``, ``n_tdc`` and ``gate_ps`` (the run's meta). Since
    the FPGA's restarts became segments of the run, a chunk also records ``ring_dropped``
    and ``conflicts`` (the ingest's counts so far), ``sender`` (the run's, when it locked
    onto one), ``second_senders`` (other senders whose datagrams formed a
    consistent stream), ``seg`` (a restarted stream's device -> run offsets) and ``events`` (the
    restarts journaled with it): ``seg``, ``device_anchor`` (the newest on the device's
    axes, which the datagrams still use), ``sender``, ``resets``."""
    from pipeline.stream.journal import _entries, run_meta

    entries = [e for e in _entries(Path(journal) / f"{run}.index.jsonl")
               if "first_word" in e]
    meta = run_meta(journal, run)
    seqs = [e for e in entries if "seq" in e]
    if not seqs or "n_tdc" not in meta:
        return None
    n = int(meta["n_tdc"])
    top = max(seqs, key=lambda e: e["seq"])
    end = max(e["first_word"] + e["words"] for e in entries)
    anchor = (top["seq"], top.get("seq_cycle", top["first_word"] // n))
    seg = tuple(seqs[-1].get("seg", (0, 0)))
    return {"seg": seg, "device_anchor": ((anchor[0] - seg[0]) & 0xFFFFFFFF,
                                          anchor[1] - seg[1]),
            "sender": seqs[-1].get("sender"),
            "second_senders": seqs[-1].get("second_senders", []),
            "ring_dropped": int(seqs[-1].get("ring_dropped", 0)),
            "conflicts": int(seqs[-1].get("conflicts", 0)),
            "resets": [ev for e in seqs for ev in e.get("events", [])],
            "next_cycle": end // n, "seq_lo": min(e.get("seq_lo", e["seq"]) for e in seqs),
            "seq_hi": top["seq"], "taken": sum(int(e.get("datagrams", 1)) for e in seqs),
            "late": int(seqs[-1].get("late", 0)),
            "anchor": anchor,
            "gap_cycles": end // n - sum(e["words"] for e in entries) // n, "n_tdc": n,
            "gate_ps": round(float(meta["t_laser_win_ns"]) * 1000)}
