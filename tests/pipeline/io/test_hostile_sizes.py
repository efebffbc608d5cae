"""Small files that claim huge sizes (issue 36, point 6): each is refused in one line before
anything is allocated. The attacks run in a subprocess whose address space is capped at
1 GiB, so a reader that believes the claim fails there (MemoryError, a traceback) instead of
taking the machine's memory."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

CAP = 1 << 30


def _capped(code: str, tmp_path: Path) -> subprocess.CompletedProcess:
    pre = textwrap.dedent(f"""
        import resource, sys
        resource.setrlimit(resource.RLIMIT_AS, ({CAP}, {CAP}))
        sys.path.insert(0, {os.getcwd()!r})
    """)
    return subprocess.run([sys.executable, "-c", pre + textwrap.dedent(code)], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)


def test_nohit_frame_claiming_4g_words_is_refused(tmp_path):
    """A 30-byte .bin.nhz whose frame header claims 2^32-1 words: refused by the header's
    count, not by a 16 GiB allocation."""
    zstandard = pytest.importorskip("zstandard")
    from pipeline.io import nohit

    head = nohit.HEADER.pack(nohit.MAGIC, 8, 0xFFFFFFFF, 0)
    (tmp_path / "bomb.bin.nhz").write_bytes(
        zstandard.ZstdCompressor().compress(head + b"\0" * 4096))
    (tmp_path / "bomb.json").write_text(json.dumps(
        {"format": "tcspc-raw", "version": 1, "n_tdc": 8, "cycles": 1000,
         "t_laser_win_ns": 100, "window_ns": 80}))
    r = _capped("""
        from pipeline.io.capture import Capture
        from schemas.errors import CaptureError
        try:
            Capture("bomb.bin.nhz").read_words(0, 8000)
        except CaptureError as exc:
            print("refused:", exc)
    """, tmp_path)
    assert r.returncode == 0, r.stderr[-400:]
    assert ("refused: bomb.bin.nhz: corrupt compressed capture: the frame header claims "
            "4294967295 words, more than a frame may hold") in r.stdout


def test_nohit_decode_refuses_a_claim_beyond_the_limit():
    from pipeline.io import nohit

    head = nohit.HEADER.pack(nohit.MAGIC, 8, nohit.MAX_FRAME_WORDS + 8, 0)
    with pytest.raises(nohit.FrameError, match="more than a frame may hold"):
        nohit.decode(head + b"\0" * ((nohit.MAX_FRAME_WORDS + 8) // 8))


def test_ptu_sparse_string_tag_is_refused(tmp_path):
    """A PTU file (sparse: a few KiB on disk) with a 1 GiB string tag: refused by the tag's
    length, not read."""
    from pipeline.io import ptu

    path = tmp_path / "sparse.ptu"
    with open(path, "wb") as fh:
        fh.write(ptu.MAGIC + b"1.0.00\0\0")
        fh.write(ptu._TAG.pack(b"File_Comment", -1, ptu.TY_ANSISTRING, 1 << 30))
        fh.truncate(16 + ptu._TAG.size + (1 << 30) + 4096)
    r = _capped("""
        from pipeline.io.ptu import PtuError, read_header
        try:
            read_header("sparse.ptu")
        except PtuError as exc:
            print("refused:", exc)
    """, tmp_path)
    assert r.returncode == 0, r.stderr[-400:]
    assert "more than a tag may hold" in r.stdout


def test_ptu_tag_flood_is_refused(tmp_path):
    from pipeline.io import ptu

    path = tmp_path / "flood.ptu"
    tags = b"".join(ptu._TAG.pack(b"Junk", i, ptu.TY_INT8, 0) for i in range(ptu.MAX_TAGS + 1))
    path.write_bytes(ptu.MAGIC + b"1.0.00\0\0" + tags)
    with pytest.raises(ptu.PtuError, match=f"more than {ptu.MAX_TAGS} tags"):
        ptu.read_header(path)


def test_deep_toml_topology_is_one_line(tmp_path):
    """Nested arrays 100 000 deep: one line naming the file, no RecursionError."""
    from pipeline.stream.topology import TopologyError, load_topology

    path = tmp_path / "deep.toml"
    path.write_text("a = " + "[" * 100_000 + "]" * 100_000 + "\n")
    with pytest.raises(TopologyError) as exc:
        load_topology(path)
    assert str(exc.value).count("\n") == 0 and str(path) in str(exc.value)


def test_unknown_key_flood_is_capped(tmp_path):
    """A topology of 40 000 unknown keys: at most 21 lines of error, the rest counted; a
    file beyond the 1 MiB limit is refused by its size."""
    from pipeline.io.limits import MAX_CONFIG_BYTES, MAX_PROBLEMS
    from pipeline.stream.topology import TopologyError, load_topology

    path = tmp_path / "flood.toml"
    path.write_text("[source]\nkind = 'sim'\n"
                    + "".join(f"k{i} = 1\n" for i in range(40_000))
                    + "".join(f"[s{i}]\n" for i in range(20_000)))
    assert path.stat().st_size < MAX_CONFIG_BYTES
    with pytest.raises(TopologyError) as exc:
        load_topology(path)
    lines = str(exc.value).splitlines()
    assert len(lines) == MAX_PROBLEMS + 1 and lines[-1].startswith("... and ")
    big = tmp_path / "big.toml"
    big.write_text("# " + "x" * MAX_CONFIG_BYTES + "\n")
    with pytest.raises(TopologyError, match="more than a topology file may hold"):
        load_topology(big)


def test_sidecar_fifo_and_size(tmp_path):
    """A sidecar that is a named pipe or over 64 MiB is refused without blocking or reading
    it."""
    from pipeline.io.capture import MAX_SIDECAR_BYTES, Capture
    from schemas.errors import CaptureError

    (tmp_path / "c.bin").write_bytes(b"\0" * 32)
    os.mkfifo(tmp_path / "c.json")
    with pytest.raises(CaptureError, match="sidecar not found"):
        Capture(tmp_path / "c.bin")
    os.unlink(tmp_path / "c.json")
    with open(tmp_path / "c.json", "wb") as fh:  # (sparse)
        fh.truncate(MAX_SIDECAR_BYTES + 1)
    with pytest.raises(CaptureError, match="more than a sidecar may hold"):
        Capture(tmp_path / "c.bin")



def test_deep_toml_scene_is_one_line(tmp_path):
    from stages.models.scene import SceneError, load_scene

    path = tmp_path / "deep.toml"
    path.write_text("a = " + "[" * 100_000 + "]" * 100_000 + "\n")
    with pytest.raises(SceneError, match="nested too deeply"):
        load_scene(path)
