"""Publishing never leaves the published path missing: a reader polling it while it is
replaced many times always finds it."""

import os
import threading

import pytest

from pipeline.io.atomic import atomic_path, exchange, point_link


def _watch(path, stop, seen):
    while not stop.is_set():
        try:
            seen.append(sorted(os.listdir(path)))
        except FileNotFoundError:
            seen.append(None)


@pytest.mark.parametrize("how", ["link", "directory"])
def test_a_reader_never_finds_the_path_missing(tmp_path, how):
    cur = tmp_path / "current"
    if how == "link":
        (tmp_path / "v0").mkdir()
        (tmp_path / "v0" / "meta.json").write_text("0")
        point_link(cur, tmp_path / "v0")
    else:
        if not exchange(tmp_path, tmp_path):  # probe: no renameat2 here
            pytest.skip("no RENAME_EXCHANGE on this system")
        cur.mkdir()
        (cur / "meta.json").write_text("0")
    stop, seen = threading.Event(), []
    reader = threading.Thread(target=_watch, args=(cur, stop, seen))
    reader.start()
    try:
        for i in range(1, 150):
            if how == "link":
                v = tmp_path / f"v{i}"
                v.mkdir()
                (v / "meta.json").write_text(str(i))
                assert point_link(cur, v) is None
            else:
                with atomic_path(cur) as tmp:
                    tmp.mkdir()
                    (tmp / "meta.json").write_text(str(i))
    finally:
        stop.set()
        reader.join()
    # never missing (a reader that opened the old directory just before the swap may
    # list it emptied by the clean-up: that is the old one going, not a gap)
    assert seen and None not in seen
    assert all(s in (["meta.json"], []) for s in seen)
    assert seen.count(["meta.json"]) > len(seen) // 2
    assert (cur / "meta.json").read_text() == "149"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_a_directory_becomes_a_link_in_one_step(tmp_path):
    cur, v1 = tmp_path / "current", tmp_path / "v1"
    cur.mkdir()
    (cur / "old").write_text("old")
    v1.mkdir()
    old = point_link(cur, v1)
    assert cur.is_symlink() and os.readlink(cur) == "v1"
    assert (old / "old").read_text() == "old"  # handed back, for the caller to keep
