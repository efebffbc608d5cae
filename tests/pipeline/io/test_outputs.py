"""The output policy (docs/design.md "Outputs: never lost, never silently replaced"):
pipeline.io.atomic.check_output, every refusal named with the user's path."""

from __future__ import annotations

import os
import shutil
from collections import namedtuple

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from pipeline.io import atomic
from pipeline.io.atomic import OutputError, check_output


def _parquet(path, schema_name=None):
    meta = {b"tcspc.schema": schema_name.encode()} if schema_name else None
    pq.write_table(pa.table({"x": [1]}).replace_schema_metadata(meta), path)
    return path


def test_a_new_output_passes_and_an_existing_one_needs_overwrite(tmp_path):
    out = tmp_path / "a" / "b" / "h.parquet"
    assert check_output(out, schema="histograms") == out  # (its directories are made later)
    _parquet(tmp_path / "h.parquet", "histograms")
    with pytest.raises(OutputError, match=r"--out .*h\.parquet: exists; give --overwrite"):
        check_output(tmp_path / "h.parquet", schema="histograms")
    check_output(tmp_path / "h.parquet", schema="histograms", overwrite=True)


@pytest.mark.parametrize("existing, how, said", [
    ("ranges.parquet", {"schema": "histograms"}, "holds a ranges table, not histograms"),
    ("plain.parquet", {"schema": "histograms"}, "a parquet table not of this tool"),
    ("pic.png", {"schema": "histograms"}, "is not a parquet file"),
    ("adir", {}, "a directory; --out takes a file path"),
    ("cap.json", {"kind": "capture"}, "not a capture's sidecar"),
])
def test_another_kind_is_never_replaced(tmp_path, existing, how, said):
    _parquet(tmp_path / "ranges.parquet", "ranges")
    _parquet(tmp_path / "plain.parquet")
    (tmp_path / "pic.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    (tmp_path / "adir").mkdir()
    (tmp_path / "cap.json").write_text("my notes")
    with pytest.raises(OutputError, match=said):
        check_output(tmp_path / existing, overwrite=True, **how)


def test_a_directory_output(tmp_path):
    (tmp_path / "empty").mkdir()
    check_output(tmp_path / "empty", "dir", contents=("tdc.parquet",))
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("x")
    with pytest.raises(OutputError, match="holds other files"):
        check_output(tmp_path / "mine", "dir", overwrite=True, contents=("tdc.parquet",))
    (tmp_path / "cal").mkdir()
    (tmp_path / "cal" / "tdc.parquet").write_bytes(b"PAR1")
    with pytest.raises(OutputError, match="exists; give --overwrite"):
        check_output(tmp_path / "cal", "dir", contents=("tdc.parquet",))
    check_output(tmp_path / "cal", "dir", overwrite=True, contents=("tdc.parquet",))
    (tmp_path / "f").write_text("x")
    with pytest.raises(OutputError, match="a file; --out takes a directory"):
        check_output(tmp_path / "f", "dir", overwrite=True)


def test_a_path_that_cannot_be_written_is_refused_first(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match=r"cannot be written: .*file is a file"):
        check_output(tmp_path / "file" / "sub" / "x.parquet")
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    with pytest.raises(OutputError, match="broken symbolic link"):
        check_output(tmp_path / "dangling", overwrite=True)
    with pytest.raises(OutputError, match="an empty path"):
        check_output("")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes anywhere")
def test_a_read_only_directory_is_named(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(OutputError, match=f"{ro} is not writable"):
            check_output(ro / "x.parquet")
    finally:
        ro.chmod(0o700)


def test_no_room_is_refused_with_the_numbers(tmp_path, monkeypatch):
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**12, 0, 10**9))
    check_output(tmp_path / "c.bin", "capture", expected_bytes=5e8)
    with pytest.raises(OutputError, match=r"needs ~5.12 PB, 1 GB free"):
        check_output(tmp_path / "c.bin", "capture", expected_bytes=5.12e15)
    assert atomic.HEADROOM_BYTES == 64 << 20  # (docs/design.md says 64 MiB)
    with pytest.raises(OutputError, match="needs ~"):  # the margin counts
        check_output(tmp_path / "c.bin", "capture", expected_bytes=10**9 - 10**6)
