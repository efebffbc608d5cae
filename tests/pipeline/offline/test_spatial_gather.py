"""The range stage's join of a fan-out by TDC range for spatial ranging
(pipeline/offline/spatial.py ``FrameGather``, ``RangeCore(spatial=..., hold=...)``):
a measurement's parts gathered into its frame whatever their order, at most ``hold``
measurements held, a part that never comes ranged around and flagged, never waited for."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.offline.spatial import FrameGather
from pipeline.stream.fanout import equal_ranges
from schemas.errors import Rejected
from stages.histogram import HistogramState

N = 16
RANGES = equal_ranges(N, 3)  # (0, 5), (5, 11), (11, 16): they cut a 4 x 4 image's rows


def _measurement(k: int, seed: int = 0) -> HistogramState:
    rng = np.random.default_rng(seed + 1000 * k)
    hits = rng.poisson(3.0, (N, 512)).astype(np.uint64)
    cc = np.zeros((5, N), np.uint64)
    cc[0] = hits.sum(1)
    cc[1] = 5000 - cc[0]
    return HistogramState(hits, cc, int(cc.sum()))


def _part(k: int, state: HistogramState, a: int, b: int, **extra):
    part = HistogramState(state.hits[a:b], state.class_counts[:, a:b],
                          int(state.class_counts[:, a:b].sum()), tdc_offset=a)
    head = {"kind": "data", "schema": "histograms", "run": "r", "seq": k,
            "step": f"histogram-{RANGES.index((a, b)) if (a, b) in RANGES else 0}",
            "measurement": f"r-m{k:06d}", "measurement_index": k, "partial": False,
            "tdc_range": [a, b], "n_tdc_total": N, "words": part.words,
            "cycles": [k * 5000, (k + 1) * 5000], "t_laser_win_ns": 140.0, **extra}
    return head, part.to_table(head["measurement"]).to_batches()[0]


@settings(max_examples=40, deadline=None)
@given(st.permutations(range(3 * len(RANGES))))
def test_parts_in_any_order_and_interleaved_give_each_frame_once_whole(order):
    """Three measurements of three parts each, in any order: each frame given back once,
    when its last part comes, every TDC's histogram its own, the first part's header with
    the frame's TDC range."""
    states = [_measurement(k) for k in range(3)]
    msgs = [_part(k, states[k], a, b) for k in range(3) for a, b in RANGES]
    g = FrameGather(hold=3)
    got, seen = {}, set()
    for i in order:
        head, batch = msgs[i]
        seen.add((head["measurement_index"], tuple(head["tdc_range"])))
        for f in g.add(head, batch):
            k = f.header["measurement_index"]
            assert k not in got and all((k, r) in seen for r in RANGES)
            got[k] = f
    assert sorted(got) == [0, 1, 2] and g.flush() == [] and g.incomplete == 0
    for k, f in got.items():
        assert f.missing == [] and f.absent is None
        assert np.array_equal(f.state.hits, states[k].hits)
        assert np.array_equal(f.state.class_counts, states[k].class_counts)
        assert f.header["tdc_range"] == [0, N] and "words" not in f.header
        assert [r for _, r in f.parts] == RANGES


def test_a_part_missing_at_the_end_of_the_stream_is_given_back_flagged():
    """Measurement 0 lacks the middle worker's part; measurement 1 comes whole and goes at
    once; the stream's end gives measurement 0 with what came: the missing TDCs absent,
    their rows the arrived rows' mean (the light level), counted incomplete."""
    s0, s1 = _measurement(0), _measurement(1)
    g = FrameGather()
    assert g.add(*_part(0, s0, 11, 16)) == []
    assert g.add(*_part(1, s1, 5, 11)) == []
    assert g.add(*_part(0, s0, 0, 5)) == []
    assert g.add(*_part(1, s1, 0, 5)) == []
    (f1,) = g.add(*_part(1, s1, 11, 16))
    assert f1.header["measurement_index"] == 1 and not f1.missing
    (f0,) = g.flush()
    assert f0.header["measurement_index"] == 0 and f0.missing == [(5, 11)]
    assert np.array_equal(np.flatnonzero(f0.absent), np.arange(5, 11))
    have = ~f0.absent
    assert np.array_equal(f0.state.hits[have], s0.hits[have])
    mean = np.rint(s0.hits[have].mean(0))
    assert np.array_equal(f0.state.hits[5], mean) and np.array_equal(f0.state.hits[10], mean)
    assert g.incomplete == 1 and g.flush() == []


def test_at_most_hold_measurements_are_held_the_oldest_given_back_first():
    """A worker that sends nothing: with ``hold`` 2, the third measurement pushes out the
    first (with the parts it has), and so on; never more than 2 held. A part of a
    measurement given back incomplete that comes late is gathered anew (ranged with what
    comes with it), not dropped."""
    g = FrameGather(hold=2)
    out = []
    for k in range(5):
        s = _measurement(k)
        for a, b in RANGES[:2]:
            out += [f.header["measurement_index"] for f in g.add(*_part(k, s, a, b))]
            assert len(g._open) <= 2
    assert out == [0, 1, 2]
    assert [f.header["measurement_index"] for f in g.flush()] == [3, 4]
    assert g.incomplete == 5
    (late,) = g.add(*_part(0, _measurement(0), 11, 16)) or g.flush()
    assert late.missing == [(0, 11)] and g.incomplete == 6


def test_a_part_sent_again_is_not_ranged_twice():
    """A restarted worker sends a part again (the same words): dropped and counted once
    its measurement was given back whole; while the measurement is held it replaces the
    part held. The same part with other words (partial then whole) is gathered anew."""
    s = _measurement(0)
    g = FrameGather()
    g.add(*_part(0, s, 0, 5))
    assert g.add(*_part(0, s, 0, 5)) == []                 # held: replaced
    g.add(*_part(0, s, 5, 11))
    (f,) = g.add(*_part(0, s, 11, 16))
    assert not f.missing
    assert g.add(*_part(0, s, 5, 11)) == [] and g.duplicates == 1
    assert g.flush() == []
    head, batch = _part(0, s, 5, 11, partial=True)         # not the one gathered: anew
    assert g.add(head, batch) == [] and len(g.flush()) == 1


def test_parts_that_cannot_be_one_frame_are_rejected():
    """Overlapping TDC ranges of one measurement, or a part whose rows are not its range:
    a counted rejection (the message quarantined), not a frame."""
    s = _measurement(0)
    g = FrameGather()
    g.add(*_part(0, s, 0, 5))
    with pytest.raises(Rejected, match="overlaps"):
        g.add(*_part(0, s, 4, 9))
    head, batch = _part(0, s, 5, 11)
    with pytest.raises(Rejected, match="rows"):
        g.add({**head, "tdc_range": [5, 12]}, batch)
    with pytest.raises(ValueError, match="hold"):
        FrameGather(hold=0)


def test_the_range_stage_ranges_the_gathered_frame_as_one_message(tmp_path, caldir):
    """RangeCore(spatial): a chip's measurement sent as three parts in any order gives the
    rows the same measurement gives in one message (one ranges message a part, beside its
    histograms); with the middle part missing at the stream's end, its TDCs get a row each,
    not detected, flagged, the other rows flagged, every message saying what was missing."""
    import pyarrow as pa

    from pipeline.io.caldir import load_calibration
    from pipeline.io.capture import Capture
    from pipeline.io.geometry import load_geometry
    from pipeline.offline.ranging import INCOMPLETE_FRAME, RangeCore
    from pipeline.offline.simulate import simulate_capture
    from pipeline.offline.spatial import MISSING
    from stages.histogram import HistogramAccumulator
    from stages.models.scene import scene_from_dict

    sc = scene_from_dict({"name": "e", "sensor": {"n_pixels": N},
                          "gate": {"t_laser_win_ns": 140.0, "delay_ns": 100.0},
                          "targets": [{"pixels": [0, 7], "distance_m": 1.5,
                                       "reflectivity": 0.0005, "surface": "mirror"},
                                      {"pixels": [8, 15], "distance_m": 2.5,
                                       "reflectivity": 0.0005, "surface": "mirror"}],
                          "ambient": [{"kind": "lux", "lux": 800.0}]})
    simulate_capture(sc, 4000, tmp_path / "cap", seed=5)
    cal = load_calibration(caldir)
    acc = HistogramAccumulator(N, cal.bounds)
    for first, words in Capture(tmp_path / "cap").iter_chunks():
        acc.update(words, first)
    state = acc.snapshot()
    g = tmp_path / "g.toml"
    g.write_text('name = "g16"\n[grid]\nrows = 4\ncols = 4\nfov_h_deg = 8.0\n'
                 'fov_v_deg = 8.0\n')
    geom = load_geometry(g)

    def ranges(msgs):
        t = pa.Table.from_batches([b for h, b in msgs if h["schema"] == "ranges"])
        return t.sort_by([("tdc", "ascending"), ("return_index", "ascending")])

    whole = ranges(RangeCore(cal, spatial=geom, max_returns=2).process(
        *_part(0, state, 0, N)))
    core = RangeCore(cal, spatial=geom, max_returns=2)
    out = []
    for a, b in (RANGES[2], RANGES[0], RANGES[1]):
        out += core.process(*_part(0, state, a, b))
    assert [h["schema"] for h, _ in out].count("histograms") == 3  # each passed on at once
    got = [(h["tdc_range"], b.num_rows) for h, b in out if h["schema"] == "ranges"]
    assert [r for r, _ in got] == [list(r) for r in RANGES]
    assert ranges(out).equals(whole)
    assert core.finish({}) == [] and core.incomplete_frames == 0
    # the middle worker's part never comes
    core = RangeCore(cal, spatial=geom, max_returns=2)
    out = [m for r in (RANGES[0], RANGES[2]) for m in core.process(*_part(0, state, *r))]
    assert all(h["schema"] == "histograms" for h, _ in out)
    out = core.finish({})
    assert [h["tdc_range"] for h, _ in out] == [[0, 5], [11, 16], [5, 11]]
    assert all(h["spatial_missing"] == [[5, 11]] for h, _ in out)
    assert "words" not in out[2][0] and out[0][0]["words"] == _part(0, state, 0, 5)[0]["words"]
    t = ranges(out)
    tdc = np.asarray(t.column("tdc"))
    gone = (tdc >= 5) & (tdc < 11)
    flag = np.array(t.column("flag").to_pylist())
    assert np.all(flag[gone] == MISSING) and not np.asarray(t.column("detected"))[gone].any()
    assert np.array_equal(np.unique(tdc[gone]), np.arange(5, 11))
    assert all(f.startswith(INCOMPLETE_FRAME) and "TDCs 5..10" in f for f in flag[~gone])
    assert core.incomplete_frames == 1
    # the TDCs that came are still ranged (the mirrors at 1.5 and 2.5 m)
    first = ~gone & (np.asarray(t.column("return_index")) == 0)
    d = np.asarray(t.column("distance_m"))[first]
    truth = np.where(tdc[first] < 8, 1.5, 2.5)
    assert np.all(np.abs(d - truth) < 3 * np.asarray(t.column("sigma_m"))[first])


def test_a_header_without_the_frames_size_takes_the_calibrations():
    """A part without ``n_tdc_total`` (a source that does not say it): the frame is the
    ``n_tdc`` given (the calibration's TDCs), never the part alone."""
    s = _measurement(0)
    g = FrameGather(n_tdc=N)
    head, batch = _part(0, s, 0, 5)
    del head["n_tdc_total"]
    assert g.add(head, batch) == []
    (f,) = g.flush()
    assert f.missing == [(5, 16)] and f.state.n_tdc == N
