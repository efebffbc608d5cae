"""The daemon's range stage with the neighbours (``[range] spatial = true``, issue 35.3) on a
chip of the zoo, not the simulator's default one, laid out on an odd, non-square grid, and
stopped by Ctrl-C while it holds parts of frames; and the end of a run's stream, which lost
its last measurements (docs/ranging.md "On the chip", docs/streaming.md "A stage's last
messages" and "Restarts")."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import polars as pl
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from pipeline.io.caldir import load_calibration
from pipeline.io.capture import Capture
from pipeline.io.geometry import load_geometry
from pipeline.offline.ranging import RangeCore
from pipeline.offline.simulate import simulate_capture
from pipeline.offline.spatial import UNPLACED
from pipeline.stream.topology import load_topology
from stages.histogram import HistogramAccumulator
from stages.models.scene import scene_from_dict

N = 16
#: the zoo's chip 2 on a 3 x 5 grid (tests/conftest.py ``zoo``): TDCs 0..14 placed (row =
#: tdc // 5), TDC 15 has no pixel; the three workers' TDC ranges (0..4, 5..10, 11..15) cut
#: the second and third rows
ON = ["measurement", "tdc", "return_index"]


def _edge(refl: float = 0.0005):
    """The top row (TDCs 0..4) at 1.5 m, the rest at 2.5 m, 800 lux."""
    return scene_from_dict({
        "name": "edge", "sensor": {"n_pixels": N},
        "gate": {"t_laser_win_ns": 140.0, "delay_ns": 100.0},
        "targets": [{"pixels": [0, 4], "distance_m": 1.5, "reflectivity": refl,
                     "surface": "mirror"},
                    {"pixels": [5, N - 1], "distance_m": 2.5, "reflectivity": refl,
                     "surface": "mirror"}],
        "ambient": [{"kind": "lux", "lux": 800.0}]})


#: the long capture's cycles (4.8 M words: 5 source batches of 65 536 cycles)
CYCLES = 300_000


@pytest.fixture(scope="module")
def long_capture(zoo, tmp_path_factory):
    cap = tmp_path_factory.mktemp("long") / "cap"
    simulate_capture(_edge(), CYCLES, cap, chip=zoo[0], seed=7)
    return cap


def _topology(tmp_path, cal, geom, cap, extra_source: str = "", histogram: str = "",
              daemon: str = ""):
    topo = tmp_path / "topo.toml"
    topo.write_text(f"""
[daemon]
state = "{tmp_path / 'state'}"
{daemon}
[source]
kind = "capture"
capture = "{cap}"
{extra_source}
[histogram]
workers = 3
calibration = "{cal}"
{histogram}
[range]
calibration = "{cal}"
spatial = true
max_returns = 2
geometry = "{geom}"
[sink]
out = "{tmp_path / 'out'}"
""")
    return topo


def _ranges(tmp_path, run) -> pl.DataFrame:
    return pl.read_parquet(tmp_path / "out" / "ranges" / "date=*" / f"run={run}" / "*.parquet")


def test_a_zoo_chip_on_an_odd_grid_streams_the_offline_rows(tmp_path, zoo):
    """A chip of the zoo (other LSB, DNL, INL bow, second stage and reset peak than the
    simulator's default), 16 TDCs on a 3 x 5 grid (TDC 15 without a pixel), three workers
    whose parts cut the grid's rows: the daemon writes the rows `tcspc range CAP
    --calibration C --spatial --geometry G` writes for the same capture, to the bit, TDC 15
    flagged and not detected, and the truth within 3 sigma on every detected pixel."""
    from pipeline.cli import cli
    from pipeline.stream.daemon import Supervisor

    chip, cal, geom = zoo
    cap = tmp_path / "cap"
    simulate_capture(_edge(), 6000, cap, chip=chip, seed=104)
    res = Supervisor(load_topology(_topology(tmp_path, cal, geom, cap), "z"),
                     log=lambda m: None).run()
    assert res["state"] == "finished", res["problems"]
    assert res["accounting"]["spatial_incomplete_frames"] == 0
    live = _ranges(tmp_path, "z")
    cli.main(args=["range", str(cap), "--calibration", str(cal), "--spatial", "--geometry",
                   str(geom), "--out", str(tmp_path / "off.parquet"), "-q"],
             standalone_mode=False)
    off = pl.read_parquet(tmp_path / "off.parquet")
    on = ["tdc", "return_index"]
    cols = ["distance_m", "sigma_m", "detected", "signal_counts", "flag"]
    assert live.sort(on).select(on + cols).equals(off.sort(on).select(on + cols))
    first = live.filter(pl.col("return_index") == 0).sort("tdc")
    assert first["tdc"].to_list() == list(range(N))
    assert first["flag"][N - 1] == UNPLACED and not first["detected"][N - 1]
    placed = first.head(N - 1)
    assert placed["detected"].sum() >= 13
    truth = np.where(placed["tdc"].to_numpy() < 5, 1.5, 2.5)
    det = placed["detected"].to_numpy()
    z = np.abs(placed["distance_m"].to_numpy() - truth) / placed["sigma_m"].to_numpy()
    assert z[det].max() < 3, z


def _status(state: Path) -> dict:
    try:
        return json.loads((state / "status.json").read_text())["stages"]
    except (OSError, ValueError, KeyError):
        return {}


def _daemon(topo, run):
    return subprocess.Popen([sys.executable, "-m", "pipeline.cli", "daemon", "--config",
                             str(topo), "--run", run], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _whole_frames(tmp_path, run, cal, geom, meta, n_meas) -> pl.DataFrame:
    """Each measurement's rows as its whole frame gives them in one message: its
    histograms parts from the datasets, joined, ranged apart."""
    core = RangeCore(load_calibration(cal), spatial=load_geometry(geom), max_returns=2,
                     forward_histograms=False)
    want = []
    for k in range(n_meas):
        parts = sorted((tmp_path / "out" / "histograms").rglob(f"part-{k:06d}-t*.parquet"))
        t = pa.concat_tables([pq.read_table(p).replace_schema_metadata(None)
                              for p in parts]).combine_chunks()
        head = {"run": run, "measurement": f"{run}-m{k:06d}", "measurement_index": k,
                "tdc_range": [0, N], "n_tdc_total": N, "window_ns": meta.window_ns,
                "t_laser_win_ns": meta.t_laser_win_ns}
        want += [pl.from_arrow(b) for _, b in core.process(head, t.to_batches()[0])]
    return pl.concat(want)


@pytest.mark.parametrize("how", [pytest.param("killed", marks=pytest.mark.slow), "hold1"])
def test_ctrl_c_while_the_range_stage_holds_parts_then_resume(tmp_path, zoo, long_capture,
                                                             how):
    """Ctrl-C (SIGINT to `tcspc daemon`) while the range stage holds parts of frames:
    ``killed``, the third worker stopped until the stage holds two frames without its
    parts, then killed (the daemon restarts it and it brings them from its checkpoint and
    the journal during the stop); ``hold1``, ``[range] hold = 1``, so that frames are
    ranged without a part all along, and the stop comes once one was (those are flagged,
    and ranged again whole by the interrupted run's reconciliation). The run is
    "interrupted" (exit 130); started again with the same --run it finishes (exit 0), and
    every measurement is in the datasets once: its histograms those of the capture's words
    [kMN, (k+1)MN), its ranges the rows its whole frame gives (no row twice, none flagged,
    none missing)."""
    _, cal, geom = zoo
    cap, cycles, mc = long_capture, CYCLES, 20_000
    # (``killed``: its restart 20 s after, which a stop does not wait out)
    # (``hold1``: a lower rate, so that the stop lands while the run goes on: at
    # 1e6 words/s the 4.8 M words took 5 s, the status showed a frame ranged without a
    # part after 3.1-4.2 M of them, and in a clean clone's suite the run had finished,
    # exit 0, before the stop; at 5e5, after 2.1-3.1 M; at 2.5e5 the run had finished
    # before the stop once in a full suite on 2 cores after the lines' offsets went to 0.01
    # px, 30 ms a frame more: 1.5e5)
    rate = "rate = 1e6" if how == "killed" else "rate = 1.5e5"
    topo = _topology(tmp_path, cal, geom, cap, rate, f"measurement_cycles = {mc}",
                     "restart_backoff_s = 20.0" if how == "killed" else "")
    if how == "hold1":
        topo.write_text(topo.read_text().replace("spatial = true\n", "spatial = true\nhold = 1\n"))
    state = tmp_path / "state"
    p = _daemon(topo, "c")
    stopped = None
    held = 0
    deadline = time.time() + 90
    try:
        while time.time() < deadline and p.poll() is None:
            st = _status(state)
            rng = st.get("range", {})
            if how == "hold1":  # (one held at most, and only between two parts)
                if rng.get("incomplete_frames", 0) >= 1:
                    held = rng.get("held_frames", 0)
                    break
            elif stopped is None and st.get("source", {}).get("words", 0) > 1_000_000 \
                    and st.get("histogram-2", {}).get("pid"):
                stopped = st["histogram-2"]["pid"]
                os.kill(stopped, signal.SIGSTOP)
            elif stopped is not None and rng.get("held_frames", 0) >= 2:
                held = rng["held_frames"]
                os.kill(stopped, signal.SIGKILL)
                break
            time.sleep(0.05)
        assert held >= 2 or how == "hold1", "the range stage never held two frames"
        assert p.poll() is None, "the run ended before the stop"
        p.send_signal(signal.SIGINT)
        t0 = time.monotonic()
        out, err = p.communicate(timeout=120)
        took = time.monotonic() - t0
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130, err
    # (the stop waited out the restart's backoff: 20-25 s; 19 s, not less, for a stop that
    # reconciles under a loaded CI runner: 15.3 s once at load 6-8)
    assert took < 19, took
    first = json.loads(out)
    assert first["state"] == "interrupted", first["problems"]
    stopped_at = first["accounting"]["words_in"]
    assert stopped_at < cycles * N
    rec = first["reconciled"]
    print(f"{how}: held {held} at the stop, after {stopped_at:,} of {cycles * N:,} words, "
          f"stopped in {took:.1f} s; first run: frames without a part",
          first["accounting"]["spatial_incomplete_frames"], "ranged again",
          rec["spatial_reranged"], "parts recomputed", rec["recomputed"])
    if how == "hold1":
        assert first["accounting"]["spatial_incomplete_frames"] >= 1
        assert rec["spatial_reranged"]
    assert rec["spatial_incomplete"] == []
    # resumed
    p = _daemon(topo, "c")
    out, err = p.communicate(timeout=240)
    assert p.returncode == 0, err
    res = json.loads(out)
    assert res["state"] == "finished" and res["accounting"]["words_in"] == cycles * N
    assert res["accounting"]["balanced"] and not res["problems"]
    # (every part reached the datasets by the stream, none recomputed at the end)
    assert res["reconciled"]["recomputed"] == [], res["reconciled"]
    n_meas = cycles // mc
    live = _ranges(tmp_path, "c")
    assert live.select(ON).n_unique() == live.height  # no row twice
    assert live["measurement"].n_unique() == n_meas
    assert (live["flag"].filter(live["tdc"] < N - 1) == "").all()
    assert live.filter(pl.col("return_index") == 0).height == n_meas * N  # none missing
    meta = Capture(cap).meta
    want = _whole_frames(tmp_path, "c", cal, geom, meta, n_meas)
    assert live.sort(ON).equals(want.sort(ON))
    # the histograms: each measurement once, the capture's words
    h = pl.read_parquet(tmp_path / "out" / "histograms" / "date=*" / "run=c" / "*.parquet")
    assert h.height == n_meas * N
    words = np.concatenate([w.copy() for _, w in Capture(cap).iter_chunks()])  # (a ring)
    bounds = load_calibration(cal).bounds
    for k in range(n_meas):
        acc = HistogramAccumulator(N, bounds)
        acc.update(words[k * mc * N:(k + 1) * mc * N], 0)
        m = h.filter(pl.col("measurement") == f"c-m{k:06d}").sort("tdc")
        assert np.array_equal(np.stack(m["counts"].to_numpy()), acc.snapshot().hits), k


@pytest.mark.parametrize("case", [pytest.param("plain", marks=pytest.mark.slow), "spatial",
                                  "spatial-one-batch-hold-8"])
def test_a_runs_last_measurements_reach_the_range_stage_by_the_stream(tmp_path, zoo,
                                                                        long_capture, case):
    """60 measurements, three workers, as fast as they go: every part reaches the datasets
    by the stream (nothing recomputed by the reconciliation) and, with the neighbours and
    the default ``hold``, every frame is gathered whole live (nothing ranged again at the
    end). ``plain`` and ``spatial``: 5000 cycles a measurement, 5 source batches. Seen
    before: the workers' last two measurements and their stops were lost on the way to
    the range stage on every such run (ZeroMQ's ipc transport loses what a consumer with a
    full queue has not read when its producer closes: pipeline.stream.hangup), and 38 of
    the 60 frames were ranged without a part live, the default ``hold`` (22) under how far
    a worker can be ahead of another (pipeline.stream.topology.range_hold: now 134).
    ``spatial-one-batch-hold-8``: 100 cycles a measurement, the whole capture one source
    batch, so that each worker sends its 60 at once to a range stage that ranges each
    frame up to three times (``hold = 8``): the workers, blocked on it after the source
    ended, were taken for stuck and SIGTERMed 3 s later, and their last 4 measurements
    given up (the daemon now counts a message sent as progress)."""
    from pipeline.stream.daemon import Supervisor

    chip, cal, geom = zoo
    cap, mc = long_capture, 5000
    if case == "spatial-one-batch-hold-8":
        cap, mc = tmp_path / "short", 100
        simulate_capture(_edge(), 6000, cap, chip=chip, seed=5)
    topo = _topology(tmp_path, cal, geom, cap, histogram=f"measurement_cycles = {mc}")
    text = topo.read_text()
    if case == "plain":
        text = text.replace("spatial = true\n", "").replace(f'geometry = "{geom}"\n', "")
    elif case == "spatial-one-batch-hold-8":
        text = text.replace("spatial = true\n", "spatial = true\nhold = 8\n")
    topo.write_text(text)
    res = Supervisor(load_topology(topo, "e"), log=lambda m: None).run()
    assert res["state"] == "finished", res["problems"]
    rec = res["reconciled"]
    assert rec["recomputed"] == [] and rec["rebuilt"] == [], rec
    if case == "spatial":
        assert rec["spatial_reranged"] == [] and rec["spatial_incomplete"] == []
        assert res["accounting"]["spatial_incomplete_frames"] == 0
    live = _ranges(tmp_path, "e")
    assert live["measurement"].n_unique() == 60
    # (no frame left ranged without a part; 100 cycles leave some pixels "before the zero")
    assert not live["flag"].str.contains("part").any()
