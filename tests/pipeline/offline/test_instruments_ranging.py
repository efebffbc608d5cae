"""Ranging a PicoQuant T3 file on the instrument's own uniform time axis: synthetic files
whose records are written here from PicoQuant's published HydraHarp V2 T3 layout (not by the
code under test), with a known delay and distance."""

from pathlib import Path

import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner
from scipy.constants import c as C_LIGHT

from pipeline.cli.app import cli
from pipeline.io.ptu import write_ptu

HH2_T3 = 0x01010304
RES_S = 16e-12
SYNC_HZ = 5e6


def t3_records(distance_m, delay_s, n_sync, rng, p_signal=0.08, p_bg=0.02,
               sigma_s=40e-12, channels=(0, 1)):
    """HydraHarp V2 T3 records: bit 31 special, 30:25 channel, 24:10 dtime, 9:0 nsync; an
    overflow (special, channel 63) every 1024 syncs, its nsync field the count (1 here)."""
    period = 1 / SYNC_HZ
    keys, words = [], []
    for ch in channels:
        sync = np.flatnonzero(rng.random(n_sync) < p_signal + p_bg)
        signal = rng.random(sync.size) < p_signal / (p_signal + p_bg)
        t = np.where(signal, delay_s + 2 * distance_m / C_LIGHT
                     + rng.normal(0, sigma_s, sync.size), rng.uniform(0, period, sync.size))
        t = np.clip(t, 0, period - RES_S)
        dtime = (t / RES_S).astype(np.int64)
        keys.append(sync * 2 + 1)
        words.append((ch << 25) | (dtime << 10) | (sync % 1024))
    blocks = np.arange(1, -(-n_sync // 1024))
    keys.append(blocks * 1024 * 2)
    words.append(np.full(blocks.size, (1 << 31) | (63 << 25) | 1, np.int64))
    keys, words = np.concatenate(keys), np.concatenate(words)
    return words[np.argsort(keys, kind="stable")].astype(np.uint32)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("t3")
    rng = np.random.default_rng(7)
    out = {}
    for name, dist in (("zero", 0.0), ("near", 1.5), ("far", 7.2)):
        out[name] = write_ptu(d / f"{name}.ptu", HH2_T3,
                              t3_records(dist, 31.3e-9, 200_000, rng),
                              resolution_s=RES_S, sync_rate_hz=SYNC_HZ,
                              tags={"HWInpChan_Enabled(0)": True,
                                    "HWInpChan_Enabled(1)": True})
    return out


def _range(tmp_path, target, *args):
    out = tmp_path / "r.parquet"
    res = CliRunner().invoke(cli, ["range", str(target), "--out", str(out), "--overwrite",
                                   *args])
    return res, (pl.read_parquet(out) if out.exists() else None)


@pytest.mark.parametrize("name, dist", [("near", 1.5), ("far", 7.2)])
def test_range_with_a_measured_delay(tmp_path, files, name, dist):
    res, r = _range(tmp_path, files[name], "--zero", str(files["zero"]))
    assert res.exit_code == 0, res.output
    assert "no INL applied" in " ".join(res.output.split())
    assert r["detected"].all() and r.height == 2
    # 16 000 signal photons, 40 ps jitter: sigma of the mean ~0.05 mm; both files' peaks
    # are measured, so the error is sqrt(2) x that, plus binning
    assert (r["distance_m"] - dist).abs().max() < 1e-3, r
    assert (r["sigma_m"] < 1e-3).all()


def test_range_with_a_given_delay_and_a_gate(tmp_path, files):
    res, r = _range(tmp_path, files["far"], "--delay-ps", "31300", "--gate", "20:150")
    assert res.exit_code == 0, res.output
    assert (r["distance_m"] - 7.2).abs().max() < 1e-3
    # (--p-fa is per bin: 3000 background-only bins in the gate)
    res, r = _range(tmp_path, files["far"], "--delay-ps", "31300", "--gate", "100:150",
                    "--p-fa", "1e-7")
    assert res.exit_code == 0 and not r["detected"].any()  # the return is outside the gate


def test_range_of_histograms_equals_range_of_the_file(tmp_path, files):
    h = tmp_path / "h.parquet"
    assert CliRunner().invoke(cli, ["histogram", str(files["near"]), "--out", str(h),
                                    "-q"]).exit_code == 0
    _, a = _range(tmp_path, files["near"], "--delay-ps", "31300")
    _, b = _range(tmp_path, h, "--delay-ps", "31300")
    assert np.allclose(a["distance_m"].to_numpy(), b["distance_m"].to_numpy(), rtol=0,
                       atol=1e-12)


def test_range_refusals(tmp_path, files):
    res, _ = _range(tmp_path, files["near"])
    assert res.exit_code != 0 and "--delay-ps or --zero" in res.output
    res, _ = _range(tmp_path, files["near"], "--delay-ps", "1", "--zero", str(files["zero"]))
    assert res.exit_code != 0
    res, _ = _range(tmp_path, files["near"], "--delay-ps", "1", "--gate", "5")
    assert res.exit_code != 0 and "LO:HI" in res.output
    lino = Path(__file__).parents[2] / "data" / "linospad2" / "test_data_2212b.dat"
    res, _ = _range(tmp_path, lino, "--delay-ps", "1", "--format", "linospad2")
    assert res.exit_code == 2 and "not a time-of-flight histogram" in res.output
