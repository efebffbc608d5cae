"""The simulator: exact engines, the chip's characteristics, and what its captures decode to."""

from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from stages.codec import classify_words
from stages.models.scene import evaluate, load_scene, scene_from_dict
from stages.models.tcspc import first_photon_histogram
from stages.simulator.chip import make_chip, second_stage
from stages.simulator.engines import (
    KIND_PHOTON,
    CodeTable,
    FastEngine,
    Optics,
    ReferenceEngine,
)
from stages.simulator.source import CHUNK_CYCLES, Simulator

SCENES = Path(__file__).parents[3] / "scenes"
WINDOW, RESET, SIGMA, TOF = 80e-9, 20e-9, 0.18e-9, 40e-9


def one_tdc(m, sbr):
    bg = m / (sbr * WINDOW) if m > 0 else 1e6
    return Optics(np.array([m]), np.array([TOF]), SIGMA, np.array([bg]), WINDOW, RESET)


def arrival_histogram(engine, rng, cycles, bins):
    """Histogram of the first-START times (photons) in arrival order, plus reset/none."""
    counts = np.zeros(bins.size + 1)
    none = 0
    done = 0
    while done < cycles:
        n = min(100_000, cycles - done)
        st = engine.draw(rng, n)
        t = st.t_s[st.kind == KIND_PHOTON]
        counts[:-1] += np.histogram(t, bins=np.concatenate([bins, [WINDOW]]))[0]
        counts[-1] += np.sum(t < 0)
        none += n - st.index.size
        done += n
    return counts, none


def expected(m, sbr, bins):
    o = one_tdc(m, sbr)
    h = first_photon_histogram(o.m_signal[0], TOF, SIGMA, o.bg_hz[0], WINDOW,
                               bins[1] - bins[0], RESET)
    return np.concatenate([h.p, [h.p_reset]]), float(h.p_none)


@pytest.mark.parametrize("m", [0.01, 0.1, 1.0, 5.0])
@pytest.mark.parametrize("sbr", [0.01, 1.0, 100.0])
def test_fast_engine_matches_the_analytic_histogram(m, sbr):
    """Chi-square p > 0.01 at 1e6 cycles, arrival times in 0.2 ns bins (models issue)."""
    chip = make_chip(1, 0, inl_scale=0.0, artifact_rate=0.0)
    o = one_tdc(m, sbr)
    eng = FastEngine(chip, o, chip.boundaries_s(0.0))
    bins = np.arange(0, WINDOW, 0.2e-9)
    obs, none = arrival_histogram(eng, np.random.default_rng(int(m * 100 + sbr)), 1_000_000,
                                  bins)
    p, p_none = expected(m, sbr, bins)
    _chisq_ok(np.append(obs, none), 1_000_000 * np.append(p, p_none))


@pytest.mark.parametrize("m, sbr", [(0.01, 0.01), (0.1, 1.0), (1.0, 1.0), (5.0, 100.0),
                                    (1.0, 100.0), (0.1, 0.01)])
def test_reference_engine_matches_the_analytic_histogram(m, sbr):
    chip = make_chip(1, 0, inl_scale=0.0, artifact_rate=0.0)
    o = one_tdc(m, sbr)
    eng = ReferenceEngine(chip, o, chip.boundaries_s(0.0), spad_sigma_s=0.17e-9)
    bins = np.arange(0, WINDOW, 0.2e-9)
    obs, none = arrival_histogram(eng, np.random.default_rng(7), 1_000_000, bins)
    p, p_none = expected(m, sbr, bins)
    _chisq_ok(np.append(obs, none), 1_000_000 * np.append(p, p_none))


@pytest.mark.slow
@pytest.mark.parametrize("m", [1.0, 5.0])
def test_reference_engine_in_heavy_background(m):
    """SBR 0.01 at M >= 1 is 100-500 background photons per cycle: slow by design."""
    chip = make_chip(1, 0, inl_scale=0.0, artifact_rate=0.0)
    o = one_tdc(m, 0.01)
    eng = ReferenceEngine(chip, o, chip.boundaries_s(0.0), spad_sigma_s=0.17e-9)
    bins = np.arange(0, WINDOW, 0.2e-9)
    obs, none = arrival_histogram(eng, np.random.default_rng(8), 1_000_000, bins)
    p, p_none = expected(m, 0.01, bins)
    _chisq_ok(np.append(obs, none), 1_000_000 * np.append(p, p_none))


def _chisq_ok(obs, exp):
    small = exp < 5
    o = np.concatenate([obs[~small], [obs[small].sum()]])
    e = np.concatenate([exp[~small], [exp[small].sum()]])
    if e[-1] == 0:
        assert o[-1] == 0
        o, e = o[:-1], e[:-1]
    e = e * o.sum() / e.sum()
    assert stats.chisquare(o, e).pvalue > 0.01


@pytest.mark.parametrize("scene", ["street", "density", "long_range"])
def test_engines_agree_on_codes(scene):
    """Two-sample chi-square on the D1st histograms of both engines, pooled over the 128
    TDCs (8192 cycles: 1e6 TDC-cycles), p > 0.01."""
    sm = evaluate(load_scene(SCENES / f"{scene}.toml"))
    chip = make_chip(128, 1)
    hists = []
    for engine in ("fast", "reference"):
        sim = Simulator(sm, chip, seed=11, engine=engine)
        h = np.zeros(512)
        for _, w in sim.batches(8192):
            cls = classify_words(w, 128, 0, chip.n_min, chip.n_max)
            hits = w[cls == 0]
            h += np.bincount(((hits >> 16) & 0x3F) * 8 + _p1(hits), minlength=512)
        hists.append(h)
    a, b = hists
    keep = (a + b) >= 10
    table = np.vstack([np.append(a[keep], a[~keep].sum()), np.append(b[keep], b[~keep].sum())])
    table = table[:, table.sum(0) > 0]
    assert stats.chi2_contingency(table)[1] > 0.01


def _p1(w):
    from stages.codec import PHASE_DECODE
    return PHASE_DECODE[(w >> 12) & 0xF].astype(np.int64)


def test_compiled_and_numpy_paths_write_the_same_bytes():
    sm = evaluate(load_scene(SCENES / "street.toml"))
    chip = make_chip(128, 1)
    a = np.concatenate([w for _, w in Simulator(sm, chip, 5, compiled=True).batches(5000)])
    b = np.concatenate([w for _, w in Simulator(sm, chip, 5, compiled=False).batches(5000)])
    assert np.array_equal(a, b)


def test_same_seed_same_bytes_different_seed_different_bytes():
    sm = evaluate(load_scene(SCENES / "short_range.toml"))
    chip = make_chip(128, 1)
    a = np.concatenate([w for _, w in Simulator(sm, chip, 3).batches(3000)])
    b = np.concatenate([w for _, w in Simulator(sm, chip, 3).batches(3000)])
    c = np.concatenate([w for _, w in Simulator(sm, chip, 4).batches(3000)])
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    # chunks are independent: drawing chunk 1 alone gives the same words
    words, _ = Simulator(sm, chip, 3).chunk(1, 3000 - CHUNK_CYCLES)
    assert np.array_equal(words, a[CHUNK_CYCLES * 128:])


def test_class_counts_equal_the_truth_with_corruption():
    sm = evaluate(load_scene(SCENES / "street.toml"))
    chip = make_chip(128, 1)
    sim = Simulator(sm, chip, 9, malformed_rate=1e-3, invalid_rate=1e-3)
    w = np.concatenate([w for _, w in sim.batches(6000)])
    cls = classify_words(w, 128, 0, chip.n_min, chip.n_max)
    per_tdc = np.zeros((5, 128), np.int64)
    np.add.at(per_tdc, (cls.astype(np.int64), np.arange(w.size) % 128), 1)
    assert np.array_equal(per_tdc, sim.result.class_counts)
    assert sim.result.class_counts[3].sum() > 0 and sim.result.class_counts[4].sum() > 0


def test_chip_is_within_the_thesis_specification():
    chip = make_chip(128, 2)
    assert np.abs(chip.dnl_lsb()).max() < 0.6 and np.abs(chip.inl_lsb).max() < 3
    lsb0, lsb_hi = chip.lsb_ps(0.0), chip.lsb_ps(1.0)
    assert np.all((lsb0 >= 200) & (lsb0 <= 205))
    growth = lsb_hi - lsb0
    assert growth.max() <= 40 and growth[64] > growth[0] and growth[64] > growth[127]
    p = chip.artifact_prob
    assert np.all(p[:60] == p[0]) and p[80] < p[59] and np.all(p[100:] == p[100])
    # the periodic part of the INL repeats every VCO cycle of 8 codes
    mean_phase = np.array([chip.dnl_lsb()[:, k::8].mean() for k in range(8)])
    assert np.ptp(mean_phase) > 0.1


def test_second_stage_codes_and_nth_pdm():
    chip = make_chip(128, 3)
    rng = np.random.default_rng(0)
    t = rng.integers(0, 128, 500_000)
    code = rng.integers(0, 512, t.size)
    d2 = second_stage(chip, t, code, rng.random(t.size))
    assert np.all((d2 >= chip.n_min[t]) & (d2 <= chip.n_max[t]))
    for i in (0, 77):
        assert d2[(t == i) & (code % 8 == 0)].min() == chip.n_th[i]
        assert d2[(t == i) & (code % 8 == 4)].min() == chip.pdm[i]


def test_code_table_equals_searchsorted():
    chip = make_chip(4, 5)
    b = chip.boundaries_s(0.2)
    ct = CodeTable(b)
    rng = np.random.default_rng(1)
    tdc = rng.integers(0, 4, 100_000)
    tau = rng.random(tdc.size) * b[:, -1].max() * 1.2
    k, frac = ct.lookup(tdc, tau)
    for i in range(4):
        x = np.mod(tau[tdc == i], b[i, -1])
        np.testing.assert_array_equal(k[tdc == i], np.searchsorted(b[i], x, "right") - 1)
    assert np.all((frac >= 0) & (frac < 1))


def test_one_newton_step_is_exact_to_femtoseconds():
    sm = evaluate(load_scene(SCENES / "street.toml"))
    eng = Simulator(sm, make_chip(128, 1), 0).engine
    rng = np.random.default_rng(0)
    tdc = rng.integers(0, 128, 100_000)
    ec = rng.random(tdc.size) * eng.l_end[tdc]
    j = np.minimum((ec / eng.de[tdc]).astype(int), eng.inv.shape[1] - 2)
    args = (tdc, ec, eng.inv[tdc, j], eng.inv[tdc, j + 1], j * eng.de[tdc],
            (j + 1) * eng.de[tdc])
    assert np.abs(eng._newton(*args) - eng._newton(*args, iterations=40)).max() < 1e-14


def test_motion_needs_the_reference_engine_and_widens_the_peak():
    raw = {"targets": [{"pixels": [0, 127], "distance_m": 5.0, "reflectivity": 0.5,
                        "surface": "mirror", "velocity_m_s": 0.5}],
           "gate": {"t_laser_win_ns": 140.0}}
    moving = evaluate(scene_from_dict(raw), 4000)
    with pytest.raises(ValueError, match="moving target needs engine='reference'"):
        Simulator(moving, make_chip(128, 1), 0, engine="fast")
    still = evaluate(scene_from_dict({**raw, "targets": [{**raw["targets"][0],
                                                           "velocity_m_s": 0.0}]}), 4000)
    spreads = []
    for sm in (still, moving):
        w = np.concatenate([w for _, w in Simulator(sm, make_chip(128, 1), 0,
                                                   engine="reference").batches(4000)])
        d1 = ((w >> 16) & 0x3F) * 8
        spreads.append(np.std(d1[(w >> 12) != 0]))
    assert spreads[1] > spreads[0]
