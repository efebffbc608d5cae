"""The page's data, without a browser: status.json and the status PUB into health rows, the
datasets into measurements and the accounting identity, the sensor's maps and marks."""

import json
import os
import time

import numpy as np
import pyarrow.parquet as pq
import pytest
import zmq

from pipeline.view import datasets, render, sensor
from pipeline.view.status import (
    RateHistory,
    StatusFeed,
    daemon_state,
    datagram_counts,
    health_rows,
    read_status,
)
from schemas.constants import WORD_CLASSES

# ---------------------------------------------------------------- status


def test_no_status_file_is_said_plainly(tmp_path, vd):
    assert read_status(tmp_path) is None
    st = daemon_state(None, time.time(), tmp_path)
    assert st.kind == "absent" and "No daemon status" in st.text


def test_daemon_states_running_finished_failed_and_lost(vd):
    now = time.time()
    assert daemon_state(vd.status(now), now).kind == "running"
    assert daemon_state(vd.status(now - 30, "finished"), now).kind == "finished"
    failed = {**vd.status(now, "failed"), "result": {"failed": "sink died 11 times"}}
    assert "sink died 11 times" in daemon_state(failed, now).text
    # a running daemon that stopped writing: its pid gone (a pid that cannot exist)
    lost = daemon_state({**vd.status(now - 20), "pid": 2**22 + 12345}, now)
    assert lost.kind == "lost" and "is gone" in lost.text and "same --run" in lost.text


def test_rates_come_from_successive_heartbeats_and_not_across_a_restart(vd):
    h = RateHistory()
    t0 = 1000.0
    for i in range(4):
        h.add(vd.status(t0 + i, histogram={"heartbeat_age_s": 0.0, "pid": 7, "received": 10 * i,
                                         "words_total": 1000 * i, "health": "ok"}))
    h.add(vd.status(t0 + 3.1, histogram={"heartbeat_age_s": 0.1, "pid": 7, "received": 30,
                                       "words_total": 3000}))  # the same beat again
    assert h.words_s("histogram") == pytest.approx([1000.0] * 3)
    assert h.msgs_s("histogram") == pytest.approx([10.0] * 3)
    h.add(vd.status(t0 + 5, histogram={"heartbeat_age_s": 0.0, "pid": 8, "received": 0,
                                     "words_total": 0}))  # restarted: no rate across it
    assert len(h.msgs_s("histogram")) == 3


def test_health_rows_show_what_the_status_says_source_first(vd):
    now = time.time()
    st = vd.status(now, sink={"pid": 1, "health": "ok", "restarts": 2, "received": 5,
                           "rejected": {"bad_token": 3}, "quarantine_dropped": 1},
                source={"pid": 2, "health": "down", "restarts": 0, "sent": 9,
                        "datagrams": 100, "lost_datagrams": 4, "duplicates": 1, "late": 0})
    rows = health_rows(st)
    assert [r["stage"] for r in rows] == ["source", "sink"]
    sink = rows[1]
    assert (sink["restarts"], sink["queue"], sink["rejected"], sink["quarantine_dropped"]) \
        == (2, 2, {"bad_token": 3}, 1)
    assert datagram_counts(st) == {"datagrams": 100, "lost_datagrams": 4, "duplicates": 1,
                                   "late": 0}
    html = render.health_table(rows)
    assert 'data-stage="sink"' in html and "bad_token: 3" in html
    assert "4</b> lost" in render.datagrams(datagram_counts(st))


def test_the_feed_takes_the_published_status_and_falls_back_to_the_file(tmp_path, vd):
    from pipeline.stream.sidecar import status_endpoint

    (tmp_path / "sock").mkdir()
    (tmp_path / "status.json").write_text(json.dumps(vd.status(1.0, "finished")))
    ctx = zmq.Context()
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    pub.bind(status_endpoint(tmp_path))
    feed = StatusFeed(tmp_path, context=ctx)
    try:
        assert feed.poll()["state"] == "finished" and feed.source == "file"
        deadline = time.time() + 10
        while feed.source != "pub" and time.time() < deadline:
            pub.send(json.dumps(vd.status(2.0)).encode())  # until the SUB has joined
            time.sleep(0.05)
            feed.poll()
        assert feed.source == "pub" and feed.status["state"] == "running"
    finally:
        feed.close()
        pub.close()
        ctx.term()


# ---------------------------------------------------------------- datasets


def test_runs_and_measurements_are_found_and_followed_by_name(tmp_path, vd):
    for k in range(3):
        for first in (0, 8):
            vd.write_part(tmp_path, vd.RUN, k, first, vd.hits_for(8, k))
    vd.write_part(tmp_path, "older", 0, 0, vd.hits_for(16))
    os.utime(tmp_path / "histograms" / "date=2026-01-02" / "run=older", (1, 1))
    assert [r["run"] for r in datasets.list_runs(tmp_path)] == [vd.RUN, "older"]
    idx = datasets.RunIndex(tmp_path, vd.RUN, n_tdc=vd.N)
    assert idx.refresh() == [0, 1, 2] and idx.firsts == [0, 8]
    vd.write_part(tmp_path, vd.RUN, 3, 0, vd.hits_for(8))  # one worker's file: not complete yet
    assert idx.refresh(now=time.time()) == []
    vd.write_part(tmp_path, vd.RUN, 3, 8, vd.hits_for(8))
    assert idx.refresh(now=time.time()) == [3] and idx.latest == 3
    m = datasets.read_measurement(idx, 2)
    assert m.name == f"{vd.RUN}-m000002" and m.tdc.tolist() == list(range(vd.N))
    assert m.counts.shape == (vd.N, 512) and m.counts[0, 200] == 52
    assert m.groups == ((0, 8), (8, 8)) and m.words == m.classified
    assert datasets.read_ranges(idx, 2) is None  # a run without a range stage


def test_a_half_written_first_measurement_is_not_taken_for_the_whole_array(tmp_path, vd):
    vd.write_part(tmp_path, vd.RUN, 0, 0, vd.hits_for(8))  # worker 1's file not there yet
    idx = datasets.RunIndex(tmp_path, vd.RUN, n_tdc=vd.N)
    assert idx.refresh() == []
    vd.write_part(tmp_path, vd.RUN, 0, 8, vd.hits_for(8))
    assert idx.refresh() == [0]


def test_missing_run_and_empty_dataset(tmp_path, vd):
    assert datasets.list_runs(tmp_path / "nothing") == []
    idx = datasets.RunIndex(tmp_path, "nope")
    assert idx.refresh() == [] and idx.latest is None
    assert datasets.read_measurement(idx, 0) is None


def test_the_identity_while_running_and_at_the_end(tmp_path, vd):
    for k in range(2):
        for first in (0, 8):
            vd.write_part(tmp_path, vd.RUN, k, first, vd.hits_for(8))
    idx = datasets.RunIndex(tmp_path, vd.RUN, n_tdc=vd.N)
    idx.refresh()
    tally = datasets.Tally()
    assert tally.add(idx, idx.have["histograms"], budget_s=10) == 0
    journal = tmp_path / "journal"
    journal.mkdir()
    index = journal / f"{vd.RUN}.index.jsonl"
    m = datasets.read_measurement(idx, 0)
    index.write_text(json.dumps({"first_word": 0, "words": 2 * m.words}) + "\n"
                     + '{"first_word": 1')  # a line being written: read next time
    tally.read_journal(journal, vd.RUN)
    with open(index, "a") as fh:
        fh.write(f', "words": {m.words}}}\n')
    tally.read_journal(journal, vd.RUN)
    ident = datasets.identity(tally, None)
    assert ident["journaled"] == 3 * m.words and ident["classified"] == 2 * m.words
    assert ident["in_flight"] == m.words and ident["holds"] is None
    assert "in flight" in render.identity(ident, vd.RUN)
    acc = {"words_in": 2 * m.words, "classes": tally.classes, "classified": 2 * m.words,
           "withheld": 0, "balanced": True}
    final = datasets.identity(tally, acc)
    assert final["holds"] and 'data-holds="true"' in render.identity(final, vd.RUN)
    assert 'data-holds="false"' in render.identity({**final, "holds": False}, vd.RUN)


def test_a_measurement_whose_classes_do_not_add_up_breaks_the_identity(tmp_path, vd):
    n = vd.N
    h = vd.hits_for(n)
    cc = np.stack([h.sum(axis=1), np.full(n, 100), np.zeros(n), np.zeros(n), np.zeros(n)])
    vd.write_part(tmp_path, vd.RUN, 0, 0, h, cc)
    # the same measurement with a cycles column that disagrees with its classes
    import pyarrow as pa

    path = next((tmp_path / "histograms").rglob("*.parquet"))
    t = pq.read_table(path)
    t = t.set_column(t.schema.get_field_index("cycles"), "cycles",
                     pa.array(t["cycles"].to_numpy() + 1))
    pq.write_table(t, path)
    idx = datasets.RunIndex(tmp_path, vd.RUN, n_tdc=vd.N)
    idx.refresh()
    tally = datasets.Tally()
    tally.add(idx, idx.have["histograms"])
    assert tally.rows_off == vd.N
    assert datasets.identity(tally, None)["holds"] is False


# ---------------------------------------------------------------- the sensor


def test_layouts(vd):
    assert sensor.default_layout(128) == (16, 8)
    assert sensor.default_layout(16) == (8, 2)
    assert sensor.parse_layout("32x4", 128) == (32, 4)
    for bad in ("16x4", "x", "0x8"):
        with pytest.raises(ValueError):
            sensor.parse_layout(bad, 128)
    x, y = sensor.pixel_xy([0, 15, 16, 127], (16, 8))
    assert x.tolist() == [0, 15, 0, 15] and y.tolist() == [0, 0, 1, 7]


def test_dead_and_hot_pixels(vd):
    n_hit = np.full(8, 1000)
    n_hit[2], n_hit[5] = 0, 9000
    dead, hot = sensor.pixel_flags(n_hit, np.full(8, 20_000))
    assert np.flatnonzero(dead).tolist() == [2] and np.flatnonzero(hot).tolist() == [5]


def test_the_reset_peak_is_where_the_light_ends_not_the_highest_count(vd):
    h = vd.hits_for(4)
    h[1, 200] = 10_000  # a return higher than the reset peak
    assert sensor.reset_peak_codes(h).tolist() == [395] * 4
    assert sensor.reset_peak_codes(np.zeros((2, 512)))[0] == -1


def _calibration(n, lsb_s=205e-12, window_s=80e-9):
    from stages import calibration as cal
    from stages.calibration_set import Calibration

    rng = np.random.default_rng(1)
    width = 1 + rng.uniform(-0.2, 0.2, (n, 512))
    inl = np.cumsum(width - 1, axis=1) - (width - 1)
    dens = cal.DensityResult(np.full(n, lsb_s), np.full(n, window_s / lsb_s), width,
                             width - 1, inl, np.full(n, 1e6), np.full(n, 0.2),
                             np.ones(n, bool), np.full(n, 0.05))
    second = cal.SecondStage(*(np.full(n, v) for v in (20, 150, 40, 90)))
    return Calibration(dens, second, None, np.full(n, 3e-9), (), None,
                       {"density": {"detections_per_pixel_per_cycle": 0.2}}, "synthetic")


def test_the_return_is_marked_where_its_distance_puts_it(tmp_path, vd):
    """eq. 5.4 backwards on the time axis the range stage uses, per worker's rows."""
    import polars as pl
    from scipy.constants import c

    from stages.calibration_set import time_axis

    for first in (0, 8):
        vd.write_part(tmp_path, vd.RUN, 0, first, vd.hits_for(8))
    idx = datasets.RunIndex(tmp_path, vd.RUN, n_tdc=vd.N)
    idx.refresh()
    meas = datasets.read_measurement(idx, 0)
    calib = _calibration(vd.N)
    consts = sensor.RunConstants(80e-9, 200e-9)
    code = 200.4
    dist = []
    for first, rows in meas.groups:
        axis = time_axis(calib.rows(first, first + rows), meas.counts[first:first + rows],
                         meas.cycles[first:first + rows], consts.window_s)
        for edges in axis.tau_edges_s:
            tau = np.interp(code, np.arange(513), edges)
            dist.append(c / 2 * (consts.t_laser_win_s - 3e-9 - tau))
    ranges = pl.DataFrame({"tdc": list(range(vd.N)), "distance_m": dist,
                           "detected": [t != 3 for t in range(vd.N)]})
    got, note = sensor.return_codes(meas, ranges, calib, consts)
    assert note == ""
    assert np.isnan(got[3]) and np.allclose(np.delete(got, 3), code, atol=1e-6)
    _, note = sensor.return_codes(meas, ranges, None, consts)
    assert "no calibration" in note
    _, note = sensor.return_codes(meas, ranges, calib, sensor.RunConstants(80e-9, None))
    assert "gate is unknown" in note


def test_a_page_opened_before_the_run_marks_the_return_once_its_gate_appears(tmp_path, vd):
    """Issue 26.8: the view started before the daemon follows the run; the return is not
    marked while the run's journal meta is missing (the note says what is missing) and is
    marked from the refresh after it appears."""
    import pyarrow as pa
    from scipy.constants import c

    from pipeline.io.caldir import save_calibration
    from pipeline.view.model import ViewModel
    from stages.calibration_set import time_axis

    out, state = tmp_path / "out", tmp_path / "state"
    calib = _calibration(vd.N)
    save_calibration(calib, tmp_path / "cal", [])
    vd.write_part(out, vd.RUN, 0, 0, vd.hits_for(vd.N))
    idx = datasets.RunIndex(out, vd.RUN)
    idx.refresh()
    meas = datasets.read_measurement(idx, 0)
    axis = time_axis(calib.rows(0, vd.N), meas.counts, meas.cycles, 80e-9)
    tau = np.array([np.interp(200.4, np.arange(513), e) for e in axis.tau_edges_s])
    dist = c / 2 * (200e-9 - 3e-9 - tau)
    d = out / "ranges" / "date=2026-01-02" / f"run={vd.RUN}"
    d.mkdir(parents=True)
    pq.write_table(pa.table({"tdc": np.arange(vd.N), "distance_m": dist,
                             "detected": np.ones(vd.N, bool)}), d / "part-000000-t000.parquet")
    m = ViewModel(state, out, tmp_path / "cal", vd.RUN, feed=False)
    m.asked = time.time()
    m.refresh()
    got = m.measurement(vd.RUN, 0)
    assert np.isnan(got["return_code"]).all()
    assert "gate is unknown" in got["note"] and "no journal at" in got["note"]
    (state / "journal").mkdir(parents=True)
    m.refresh()
    assert f"{vd.RUN}.meta.json not written" in m.measurement(vd.RUN, 0)["note"]
    (state / "journal" / f"{vd.RUN}.meta.json").write_text(json.dumps(
        {"n_tdc": vd.N, "window_ns": 80.0, "t_laser_win_ns": 200.0}))
    m.refresh()
    got = m.measurement(vd.RUN, 0)
    assert got["note"] == "" and np.allclose(got["return_code"], 200.4, atol=1e-6)
    assert m.tracks[vd.RUN].index.n_tdc == vd.N  # the array's size known from then on


def test_untrusted_online_lsb_estimates_are_left_out_of_the_drift_and_named(vd, mirror16):
    """Issue 26.8: on the small scene the online LSB estimate took a return higher than the
    reset peak for tau = T (+370 ps). Now each TDC's estimate is the chip's LSB, and one
    that cannot be trusted (here: two TDCs whose calibration says 0.6 of it) is left out of
    the drift's median and band, named with why; the page's drift plot says so."""
    from pipeline.view.model import RunTrack, ViewModel
    from pipeline.view.page import drift_flag_note

    st, lsb_t, window_s = mirror16
    expected = lsb_t.copy()
    expected[[3, 11]] *= 0.6
    meas = datasets.Measurement(vd.RUN, 0, "m", np.arange(vd.N), st.cycles, st.hits,
                                {c: np.zeros(vd.N) for c in WORD_CLASSES}, ((0, vd.N),))
    d = sensor.lsb_drift(meas, _calibration(vd.N, expected, window_s), window_s)
    assert sorted(d["flagged"]) == [3, 11] and "not a drift" in d["flagged"][3]
    assert d["n"] == vd.N - 2 and max(abs(d["p10_ps"]), abs(d["p90_ps"])) < 0.5
    m = ViewModel("/nonexistent", "/nonexistent", None, feed=False)
    m.tracks[vd.RUN] = tr = RunTrack(vd.RUN, None, sensor.RunConstants(80e-9, None))
    tr.drift[0] = d
    s = m.drift_series(vd.RUN)
    assert s["k"].tolist() == [0] and sorted(s["flagged"]) == [3, 11]
    note = drift_flag_note(s["flagged"])
    assert "left out" in note and "TDC 3, 11" in note and drift_flag_note({}) == ""


def test_calibration_frames_and_the_lsb_drift_without_a_calibration(tmp_path, vd):
    calib = _calibration(vd.N)
    f = sensor.calibration_frames(calib, 0.2)
    assert f["lsb_ps"] == pytest.approx(np.full(vd.N, 205.0))
    assert f["inl_lsb"].shape == (vd.N, 512) and f["lsb_at_light_ps"] is not None
    vd.write_part(tmp_path, vd.RUN, 0, 0, vd.hits_for(vd.N))
    idx = datasets.RunIndex(tmp_path, vd.RUN)
    idx.refresh()
    meas = datasets.read_measurement(idx, 0)
    assert sensor.lsb_drift(meas, None, 80e-9)["n"] == 0


def test_an_online_lsb_that_matches_the_calibration_drifts_by_nothing(vd, mirror16):
    """A calibration holding the chip's true LSB: the online estimate on a simulated range
    measurement (its return masked) drifts by nothing on every TDC. (Was a uniform
    histogram with no reset peak, whose own density test is not a calibration.)"""
    st, lsb_t, window_s = mirror16
    meas = datasets.Measurement(vd.RUN, 0, "m", np.arange(vd.N), st.cycles, st.hits,
                                {c: np.zeros(vd.N) for c in WORD_CLASSES}, ((0, vd.N),))
    d = sensor.lsb_drift(meas, _calibration(vd.N, lsb_t, window_s), window_s)
    assert d["n"] == vd.N and abs(d["median_ps"]) < 0.5 and d["flagged"] == {}


def test_a_measurement_lost_in_flight_is_stepped_over_and_found_at_the_end(tmp_path, vd):
    for k in (0, 2, 3):  # measurement 1 lost with a killed sink; reconciled at the end
        for first in (0, 8):
            vd.write_part(tmp_path, vd.RUN, k, first, vd.hits_for(8))
    idx = datasets.RunIndex(tmp_path, vd.RUN, n_tdc=vd.N)
    idx.refresh()
    for first in (0, 8):
        vd.write_part(tmp_path, vd.RUN, 4, first, vd.hits_for(8))
    idx.refresh(now=time.time())
    assert idx.have["histograms"] == [0, 2, 3, 4]
    for first in (0, 8):
        vd.write_part(tmp_path, vd.RUN, 1, first, vd.hits_for(8))
    idx.rescan()
    assert idx.refresh() == [1] and idx.have["histograms"] == [0, 1, 2, 3, 4]
