"""Issue 33.4: another chip's calibration is refused. A capture's background carries its
chip's code-density pattern; `tcspc range` checks it against the calibration's widths
(:mod:`stages.calibration.chip_check`) before it writes anything: another chip's refused in
one line (exit 2, the TDCs named), ranged with every row flagged under --force; the same
chip recalibrated passes; a capture too dim to tell passes with a warning, never refused.

Pairs of zoo chips with what real chips have (``REAL_CHIP_RANGES``), calibrated as
`calibrate lsb` / `calibrate delay` do (benchmarks/calibration_sigma.py); captures as
Poisson draws of expected histograms with a return on every pixel (strong ones included:
a return firing in most cycles), and through the CLI as the simulator writes them."""

import dataclasses
import json

import numpy as np
import pyarrow.parquet as pq
import pytest

from benchmarks.calibration_sigma import (
    RANGE_GATE_S,
    T,
    calibrate,
    capture,
    chip_of,
    save_chip_calibration,
    simulated_capture,
)
from pipeline.offline.ranging import TDC_FLAG_SIGMAS, check_capture_chip, range_state

N = 8


@pytest.fixture(scope="module")
def cals():
    """Chips 1-3 calibrated, and chip 1 again from other noise draws."""
    out = {s: calibrate(chip_of(s, N), s) for s in (1, 2, 3)}
    out["1 again"] = calibrate(chip_of(1, N), 11)
    return out


def _check(calib, chip_seed, light, cycles, seed, m=0.05):
    rng = np.random.default_rng(seed)
    st = capture(chip_of(chip_seed, N), light, cycles, rng, np.full(N, m),
                 rng.uniform(3e-9, 77e-9, N))
    est, *_ = range_state(st, calib, T, RANGE_GATE_S, max_returns=3)
    return check_capture_chip(calib, st, est, T)


@pytest.mark.parametrize("cal_chip,cap_chip", [(1, 2), (2, 3), (3, 1), (2, 1)])
def test_another_chips_calibration_is_refused(cals, cal_chip, cap_chip):
    """A capture of 1e5 cycles at 0.1 detections a cycle: the other chip's widths differ
    by 0.11-0.17 LSB RMS a code; refused, most TDCs named."""
    ck = _check(cals[cal_chip], cap_chip, 0.1, 1e5, seed=cap_chip)
    assert ck.verdict == "mismatch", ck.summary()
    assert ck.width_diff_lsb > 0.09 and ck.disagree.sum() >= N // 2, ck.summary()


@pytest.mark.parametrize("light,cycles", [(0.02, 5e5), (0.1, 5e4), (0.3, 5e5), (0.6, 5e4)])
@pytest.mark.parametrize("m", [0.02, 0.5, 2.0])
def test_the_same_chip_recalibrated_passes(cals, light, cycles, m):
    """Chip 1's captures against its calibration and against a recalibration from other
    noise draws, returns from faint to firing in most cycles (m = 2: 86 %): never
    refused, no TDC flagged alone; decided ("match") where the background has the counts."""
    for key in (1, "1 again"):
        ck = _check(cals[key], 1, light, cycles, seed=int(light * 1000 + m * 10))
        assert ck.verdict != "mismatch", (key, ck.summary())
        assert ck.beyond_sigmas < 3, (key, ck.summary())
        assert not ck.disagree_at(TDC_FLAG_SIGMAS).any(), (key, ck.summary())
        if light * cycles >= 1.5e5:
            assert ck.verdict == "match", (key, ck.summary())


def test_a_calibration_without_its_width_variance_is_checked_too(cals):
    """A calibration made before issue 33 (or by one density test) stores no width
    variance: its INL error stands for it, so its own counting is not taken for another
    chip's widths (a bright capture of the same chip passes, another chip's is refused)."""
    old = dataclasses.replace(cals[1], width_var_lsb2=None)
    same = _check(old, 1, 0.3, 5e5, seed=1)
    assert same.verdict == "match" and same.beyond_sigmas < 3, same.summary()
    assert _check(old, 2, 0.3, 5e5, seed=1).verdict == "mismatch"


@pytest.mark.parametrize("chip_seed", [1, 2])
def test_a_dim_capture_is_undecided_never_refused(cals, chip_seed):
    """5e4 cycles at 0.005 detections a cycle: ~0.6 background counts a code, too few to
    see even another chip's widths; the verdict is "undecided" (ranged with a warning)."""
    ck = _check(cals[1], chip_seed, 0.005, 5e4, seed=7)
    assert ck.verdict == "undecided", ck.summary()
    assert ck.power_sigmas < 1


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("chips")
    cal1 = save_chip_calibration(chip_of(1, N), 1, d / "cal1")
    return {"cal1": cal1,
            "chip1": simulated_capture(chip_of(1, N), d / "chip1.bin"),
            "chip2": simulated_capture(chip_of(2, N), d / "chip2.bin"),
            "dim2": simulated_capture(chip_of(2, N), d / "dim2.bin", lux=40.0,
                                      cycles=50_000),
            "d": d}


def _range(argv, capsys):
    from pipeline.cli.app import cli

    capsys.readouterr()
    with pytest.raises(SystemExit) as ended:
        cli.main([str(a) for a in argv], prog_name="tcspc")
    return ended.value.code, capsys.readouterr().err


def test_range_refuses_another_chip_in_one_line(files, capsys):
    out = files["d"] / "r2.parquet"
    code, err = _range(["range", files["chip2"], "--calibration", files["cal1"], "--out", out],
                       capsys)
    errors = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert code == 2 and len(errors) == 1, err
    assert "does not match calibration" in errors[0] and "TDCs " in errors[0], errors
    assert f"of {N})" in errors[0] and "--force" in errors[0]
    assert not out.exists()


def test_force_ranges_another_chip_with_every_row_flagged(files, capsys):
    out = files["d"] / "r2f.parquet"
    code, err = _range(["range", files["chip2"], "--calibration", files["cal1"], "--out", out,
                        "--force"], capsys)
    assert code == 0, err
    assert "--force" in err and "not the calibration's chip" in err
    t = pq.read_table(out)
    assert all("calibration of another chip" in f for f in t.column("flag").to_pylist())
    chk = json.loads(t.schema.metadata[b"tcspc.chip_check"])
    assert chk["verdict"] == "mismatch" and len(chk["disagree"]) >= N // 2


def test_range_passes_the_same_chip_and_a_dim_capture_with_a_warning(files, capsys):
    out = files["d"] / "r1.parquet"
    code, err = _range(["range", files["chip1"], "--calibration", files["cal1"], "--out", out],
                       capsys)
    assert code == 0, err
    t = pq.read_table(out)
    assert json.loads(t.schema.metadata[b"tcspc.chip_check"])["verdict"] == "match"
    assert not any("chip" in f for f in t.column("flag").to_pylist())
    out = files["d"] / "rdim.parquet"
    code, err = _range(["range", files["dim2"], "--calibration", files["cal1"], "--out", out],
                       capsys)
    assert code == 0, err
    assert "chip not checked: too few background counts" in err
    t = pq.read_table(out)
    assert json.loads(t.schema.metadata[b"tcspc.chip_check"])["verdict"] == "undecided"


def test_force_is_refused_where_there_is_no_chip_to_check(files, capsys):
    from pathlib import Path

    t3 = Path(__file__).parents[2] / "data" / "picoquant" / "hydraharp_v20_t3.ptu"
    code, err = _range(["range", t3, "--delay-ps", "0", "--out", files["d"] / "x.parquet",
                        "--force"], capsys)
    assert code == 2 and "--force is for a tcspc capture" in err, err


def test_the_range_stage_flags_another_chips_measurements(cals):
    """The daemon's range stage checks each measurement as `tcspc range` checks a capture;
    a stream is not refused mid-run (its data are kept): another chip's rows are all
    flagged, the operator warned once, every verdict counted; the same chip's are not."""
    from pipeline.offline.ranging import CHIP_MISMATCH, RangeCore

    told: list[str] = []
    core = RangeCore(cals[1], "ml", forward_histograms=False, warn=told.append)
    flags = {}
    for chip_seed, seed in ((2, 5), (2, 6), (1, 7)):
        rng = np.random.default_rng(seed)
        st = capture(chip_of(chip_seed, N), 0.3, 5e5, rng, np.full(N, 0.05),
                     rng.uniform(3e-9, 77e-9, N))
        header = {"run": "r", "measurement": f"m{seed}", "window_ns": T * 1e9,
                  "t_laser_win_ns": RANGE_GATE_S * 1e9}
        ((head, batch),) = core.process(header, st.to_table(f"m{seed}").to_batches()[0])
        flags[seed] = (head["chip_check"], batch.column("flag").to_pylist())
    assert flags[5][0] == flags[6][0] == "mismatch"
    assert all(CHIP_MISMATCH in f for f in flags[5][1] + flags[6][1])
    assert flags[7][0] == "match" and not any(CHIP_MISMATCH in f for f in flags[7][1])
    assert core.chip_checks == {"mismatch": 2, "match": 1}
    assert len(told) == 1 and "measurement m5 does not match" in told[0], told
