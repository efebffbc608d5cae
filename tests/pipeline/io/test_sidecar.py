"""Capture sidecars (docs/design.md "Capture files"): compact JSON with what a reader needs,
the simulator's large truth arrays in NAME.truth.parquet, read only when asked for; a
sidecar written before (every array inline, indented) reads as it did."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.io.capture import (
    TRUTH_TABLE_MIN,
    Capture,
    CaptureWriter,
    LazyTruth,
    truth_table_path,
)
from schemas.errors import CaptureError
from stages.codec import encode_words

ROOT = Path(__file__).parents[3]


def _truth(rng):
    return {"generator": "test", "distance_m": [1.5, None, 3.0],
            "chip": {"inl_lsb": rng.normal(size=(8, 512)), "n_min": list(range(8)),
                     "nested": {"table": rng.normal(size=TRUTH_TABLE_MIN),
                                "counts": list(range(TRUTH_TABLE_MIN))}}}


def _write(path, truth):
    with CaptureWriter(path, n_tdc=8, kind="range", truth=truth) as w:
        w.write(encode_words(0, 0, 0, 0, np.tile(np.arange(8), 10)))


def test_large_arrays_go_beside_the_compact_sidecar_and_come_back(tmp_path):
    rng = np.random.default_rng(1)
    truth = _truth(rng)
    _write(tmp_path / "c", truth)
    text = (tmp_path / "c.json").read_text()
    assert "\n" not in text.strip() and ": " not in text  # compact: one line, no indent
    doc = json.loads(text)
    assert doc["truth"]["chip"]["inl_lsb"] == {"$truth_table": "c.truth.parquet",
                                                "key": "chip/inl_lsb"}
    assert doc["truth"]["chip"]["n_min"] == list(range(8))  # small values stay inline
    assert truth_table_path(tmp_path / "c.json").is_file()
    got = Capture(tmp_path / "c").meta.truth
    assert isinstance(got, LazyTruth)
    np.testing.assert_array_equal(np.array(got["chip"]["inl_lsb"]), truth["chip"]["inl_lsb"])
    np.testing.assert_array_equal(np.array(got["chip"]["nested"]["table"]),
                                  truth["chip"]["nested"]["table"])
    counts = got["chip"]["nested"]["counts"]  # integers come back as integers
    assert counts == list(range(TRUTH_TABLE_MIN)) and isinstance(counts[5], int)
    assert got["distance_m"] == [1.5, None, 3.0] and got.get("missing") is None
    # a copy (journal export writes the truth again) holds the arrays themselves
    again = Capture(tmp_path / "c").meta.to_dict()["truth"]
    assert np.array(again["chip"]["inl_lsb"]).shape == (8, 512)


def test_a_command_that_does_not_read_the_truth_never_opens_the_table(tmp_path):
    _write(tmp_path / "c", _truth(np.random.default_rng(2)))
    code = ("import sys; from pipeline.io.capture import Capture; "
            f"c = Capture({str(tmp_path / 'c')!r}); c.meta.truth['generator']; "
            "print('pyarrow.parquet' in sys.modules)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, env={"PYTHONPATH": str(ROOT)})
    assert res.stdout.strip() == "False", res.stderr


def test_an_old_sidecar_with_everything_inline_still_reads(tmp_path):
    rng = np.random.default_rng(3)
    truth = _truth(rng)
    _write(tmp_path / "c", {"generator": "x"})
    old = {"format": "tcspc-raw", "version": 1, "n_tdc": 8, "window_ns": 80.0,
           "t_laser_win_ns": 140.0, "cycles": 10, "kind": "range",
           "truth": json.loads(json.dumps(truth, default=lambda a: a.tolist()))}
    (tmp_path / "c.json").write_text(json.dumps(old, indent=1))  # as written before
    got = Capture(tmp_path / "c").meta.truth
    np.testing.assert_array_equal(np.array(got["chip"]["inl_lsb"]), truth["chip"]["inl_lsb"])


def test_a_missing_table_is_named_when_asked_for(tmp_path):
    _write(tmp_path / "c", _truth(np.random.default_rng(4)))
    truth_table_path(tmp_path / "c.json").unlink()
    truth = Capture(tmp_path / "c").meta.truth  # opens: the words are all there
    with pytest.raises(CaptureError, match="c.truth.parquet: not found"):
        truth["chip"]["inl_lsb"]


def test_a_capture_written_over_one_with_a_table_leaves_no_stale_table(tmp_path):
    _write(tmp_path / "c", _truth(np.random.default_rng(5)))
    _write(tmp_path / "c", {"generator": "small"})
    assert not truth_table_path(tmp_path / "c.json").exists()


def test_a_simulated_street_capture_has_a_small_sidecar(tmp_path):
    from pipeline.offline.simulate import simulate_capture
    from stages.models.scene import load_scene

    simulate_capture(load_scene(ROOT / "scenes" / "street.toml"), 200, tmp_path / "s.bin")
    assert (tmp_path / "s.json").stat().st_size < 32_000  # (1.9 MB indented before)
    chip = Capture(tmp_path / "s.bin").meta.truth["chip"]
    assert np.array(chip["inl_lsb"]).shape == (128, 512)
