"""Issue 36, point 5: the output directory ([sink] out) against another account of the
host: its owner and mode, links raced at the sink's temporaries, a planted accounting link,
and parts swapped between measurements."""

from __future__ import annotations

import os

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from pipeline.stream.state import StateError, check_output_dir, write_under

CYCLES = 30_000


def test_an_output_directory_others_may_write_is_refused(tmp_path):
    """Before: a [sink] out of mode 0777 was taken (anyone could plant links in it)."""
    out = tmp_path / "out"
    out.mkdir()
    os.chmod(out, 0o777)
    with pytest.raises(StateError, match="group- or world-writable"):
        check_output_dir(out)
    os.chmod(out, 0o755)
    check_output_dir(out)  # (readable by others is fine: datasets are shared)


def test_an_output_directory_of_another_account_is_refused(tmp_path, other_account):
    out = tmp_path / "out"
    out.mkdir()
    os.chown(out, other_account, -1)
    os.chmod(out, 0o777)
    with pytest.raises(StateError, match=f"owned by uid {other_account}"):
        check_output_dir(out)
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    os.chown(theirs, other_account, -1)
    with pytest.raises(StateError, match=f"which uid {other_account} owns"):
        check_output_dir(theirs / "out")


def test_a_link_raced_at_the_sinks_temporary_is_never_followed(tmp_path):
    """Before: the sink wrote OUT/.../.part-N.parquet.tmp-PID through a link planted there:
    a file of the operator's (here `victim`) was overwritten with parquet bytes."""
    from pipeline.stream.stage import ParquetSink
    from schemas.outputs import HISTOGRAMS

    out = tmp_path / "out"
    victim = tmp_path / "victim"
    victim.write_text("the operator's file\n")
    sink = ParquetSink(out)
    header = {"kind": "data", "schema": HISTOGRAMS.name, "run": "r", "seq": 0,
              "date": "2026-01-01", "tdc_range": [0, 4]}
    path = sink.path(header)
    path.parent.mkdir(parents=True)
    for pid in range(os.getpid() - 2, os.getpid() + 3):  # the names a racer would try
        os.symlink(victim, path.with_name(f".{path.name}.tmp-{pid}"))
    table = pa.table({"x": [1, 2, 3]})
    sink.process(header, table.to_batches()[0])
    assert victim.read_text() == "the operator's file\n"
    assert pq.read_table(path).num_rows == 3
    assert not path.is_symlink()


def test_a_planted_accounting_link_is_refused(tmp_path):
    """Before: OUT/accounting -> elsewhere made the daemon write its accounting there."""
    out, elsewhere = tmp_path / "out", tmp_path / "elsewhere"
    out.mkdir()
    elsewhere.mkdir()
    os.symlink(elsewhere, out / "accounting")
    with pytest.raises(StateError, match="symbolic link"):
        check_output_dir(out)
    with pytest.raises(StateError, match="a link is never followed"):
        write_under(out, "accounting/run=r.json", b"{}")
    assert list(elsewhere.iterdir()) == []


def test_parts_swapped_between_measurements_are_rebuilt(tmp_path, daemon_helpers):
    """Before: two parts holding each other's measurement (same TDCs, same cycles) passed
    the reconciliation and the run ended finished and balanced."""
    import polars as pl

    from pipeline.stream.reconcile import reconcile
    from pipeline.stream.topology import load_topology

    topo_path = daemon_helpers.topology(tmp_path, cycles=CYCLES, workers=1)
    res, _ = daemon_helpers.run_daemon(topo_path, "sw")
    assert res["failed"] is None and res["accounting"]["balanced"], res
    parts = sorted((tmp_path / "out" / "histograms").glob("date=*/run=sw/part-*.parquet"))
    assert len(parts) == 3
    before = {p.name: pl.read_parquet(p) for p in parts}
    a, b = parts[0], parts[1]
    tmp = a.with_name("swap")
    os.replace(a, tmp)
    os.replace(b, a)
    os.replace(tmp, b)
    rec = reconcile(load_topology(topo_path, "sw"))
    assert sorted(r["measurement"] for r in rec["rebuilt"]) == [0, 1], rec
    for p in parts:
        assert pl.read_parquet(p).equals(before[p.name])
