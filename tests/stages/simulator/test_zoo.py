"""The chip zoo's knobs (docs/simulator.md): each does what it says, the default chip is the
thesis's, and the compiled and numpy paths still write the same bytes."""

import dataclasses

import numpy as np
import pytest

from schemas.constants import N_CODES
from stages.codec import PHASE_DECODE, classify_words
from stages.models.scene import Ambient, Gate, Scene, Sensor, Target, evaluate
from stages.simulator.chip import ZOO_RANGES, make_chip, random_chip, second_stage
from stages.simulator.engines import CodeTable
from stages.simulator.source import Simulator

N = 8


def scene(lux=2009.247, target=False, reset_ns=20.0):
    """A uniform-light scene of N pixels (a density test), or a zero-distance return."""
    targets = (Target((0, N - 1), 0.001, 0.0015, "mirror"),) if target else ()
    return Scene("zoo", sensor=Sensor(n_pixels=N, hot_pixels=(), reset_ns=reset_ns),
                 gate=Gate(140.0, 100.0), targets=targets,
                 ambient=(Ambient(lux=lux),) if lux else ())


def words_of(chip, sc, cycles, seed=0, compiled=None):
    sim = Simulator(evaluate(sc, cycles), chip, seed, compiled=compiled)
    return np.concatenate([w for _, w in sim.batches(cycles)]), sim


def fields(w):
    d1 = ((w >> 16) & 0x3F).astype(np.int64) * 8 + PHASE_DECODE[(w >> 12) & 0xF]
    d2 = ((w >> 26) & 0x1F).astype(np.int64) * 8 + PHASE_DECODE[(w >> 22) & 0xF]
    return d1, d2


def hits_of(chip, w):
    cls = classify_words(w, chip.n_tdc, 0, chip.n_min, chip.n_max)
    keep = cls == 0
    return (np.arange(w.size) % chip.n_tdc)[keep], *fields(w[keep])


def test_default_knobs_are_the_thesis_chip():
    """Every knob at its default draws nothing and changes nothing."""
    a, b = make_chip(16, 7), make_chip(16, 7, d2nd_dnl=0.0, dead_codes=0, lsb_quad_ps=0.0)
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        assert (x is None and y is None) or np.array_equal(x, y), f.name
    assert a.d2nd_edges is None and a.dead_codes is None and a.reset_ns is None
    assert "d2nd_widths" not in a.truth(0.2)


@pytest.mark.parametrize("seed", [0, 1])
def test_zoo_chips_compiled_and_numpy_write_the_same_bytes(seed):
    chip, knobs = random_chip(seed, N, {"dead_codes": (3, 3), "reset_offset_ps": (-80., 80.)})
    for sc in (scene(), scene(lux=66.975, target=True)):
        a, _ = words_of(chip, sc, 3000, compiled=True)
        b, _ = words_of(chip, sc, 3000, compiled=False)
        assert np.array_equal(a, b), knobs


def test_random_chip_draws_within_the_ranges():
    for seed in range(20):
        chip, k = random_chip(seed, 4)
        for name, (lo, hi) in ZOO_RANGES.items():
            assert lo <= k[name] <= hi, name
        assert np.all(chip.n_max < 254) and np.all(chip.n_th >= chip.n_min)
        w = np.diff(chip.inl_lsb, axis=1) + 1  # every live code wider than 0.4 LSB
        dead = np.zeros(w.shape, bool) if chip.dead_codes is None else chip.dead_codes
        assert np.all(w[~dead] > 0.4) and np.all(w[dead] == 0)
    a, b = random_chip(5, 4), random_chip(5, 4)
    assert np.array_equal(a[0].inl_lsb, b[0].inl_lsb) and a[1] == b[1]


def test_second_stage_dnl_shapes_the_block_and_keeps_nth_pdm():
    """The D2nd histogram inside [Nmin, Nmax] follows the widths (tens of percent), no
    code inside is empty, none outside, and Nth / PDM stay the smallest D2nd at P1st 0 / 4."""
    chip = make_chip(4, 3, d2nd_dnl=0.4)
    rng = np.random.default_rng(0)
    t = rng.integers(0, 4, 400_000)
    code = rng.integers(0, 512, t.size)
    d2 = second_stage(chip, t, code, rng.random(t.size))
    for i in range(4):
        w = chip.width[i]
        widths = np.diff(chip.d2nd_edges[i, :w + 1]) * w
        assert widths.min() >= 0.3 / 1.4 and np.ptp(widths) > 0.4
        h = np.bincount(d2[t == i], minlength=256)
        assert np.all(h[:chip.n_min[i]] == 0) and np.all(h[chip.n_max[i] + 1:] == 0)
        mod = np.arange(w)
        d = chip.n_th[i] + mod
        d = np.where(d > chip.n_max[i], d - w, d)
        expect = widths / w * h.sum()
        assert np.all(np.abs(h[d] - expect) < 5 * np.sqrt(expect) + 1)
        assert d2[(t == i) & (code % 8 == 0)].min() == chip.n_th[i]
        assert d2[(t == i) & (code % 8 == 4)].min() == chip.pdm[i]


def test_dead_codes_are_never_output_and_their_time_goes_to_a_neighbour():
    chip = make_chip(N, 2, dead_codes=3)
    dead = chip.dead_codes
    assert dead.sum(axis=1).tolist() == [3] * N
    w = np.diff(chip.boundaries_s(0.2), axis=1)
    assert np.all(w[dead] == 0) and np.all(w[~dead] > 0)
    words, sim = words_of(chip, scene(), 30_000, compiled=False)
    x_t = chip.window_truth(sim.light, 80e-9)[1]
    tdc, d1, _ = hits_of(chip, words)
    h = np.zeros((N, N_CODES))
    np.add.at(h, (tdc, d1), 1)
    assert np.all(h[dead] == 0)
    # the neighbours that took the dead codes' time hold about two codes' counts each
    got = ref = 0.0
    for i, k in zip(*np.nonzero(dead), strict=True):
        if k + 9 > x_t[i] - 8:  # the reset peak's codes
            continue
        j = k + 1 if w[i, k + 1] > w[i, k - 1] else k - 1
        got += h[i, j]
        ref += w[i, j] * h[i, k - 8:k + 9].sum() / w[i, k - 8:k + 9].sum()
    assert 0.88 < got / ref < 1.12  # counts follow the merged width (~2 codes)


def test_code_table_skips_dead_codes():
    chip = make_chip(4, 5, dead_codes=3)
    b = chip.boundaries_s(0.2)
    ct = CodeTable(b)
    rng = np.random.default_rng(1)
    tdc = rng.integers(0, 4, 200_000)
    tau = rng.random(tdc.size) * b[:, -1].max()
    k, frac = ct.lookup(tdc, tau)
    for i in range(4):
        x = np.mod(tau[tdc == i], b[i, -1])
        np.testing.assert_array_equal(k[tdc == i], np.searchsorted(b[i], x, "right") - 1)
    assert not chip.dead_codes[tdc, k].any() and np.all((frac >= 0) & (frac < 1))


def test_lsb_curvature():
    flat, bent = make_chip(4, 1), make_chip(4, 1, lsb_quad_ps=10.0)
    np.testing.assert_array_equal(flat.lsb_ps(0.0), bent.lsb_ps(0.0))
    np.testing.assert_allclose(bent.lsb_ps(0.5) - flat.lsb_ps(0.5),
                               10.0 * 0.25 * flat.light_profile)


def test_reset_peak_height_position_and_spread():
    """The reset peak's counts grow with the chip's reset period; its offset moves it by
    offset / LSB codes; its extra jitter widens it."""
    base = make_chip(N, 4, artifact_rate=0.0)

    def peak(chip):
        words, sim = words_of(chip, scene(lux=401.849), 20_000, compiled=False)
        tdc, d1, _ = hits_of(chip, words)
        x_t = 80e-9 / (chip.lsb_ps(sim.light) * 1e-12)
        rel = d1 - x_t[tdc]
        near = np.abs(rel) < 6
        return near.sum(), rel[near].mean(), rel[near].std(), sim

    n20, m20, s20, sim = peak(base)
    n40, _, _, sim40 = peak(dataclasses.replace(base, reset_ns=40.0))
    assert sim40.optics.reset_s == 40e-9 and sim.truth()["reset_ns"] == 20.0
    assert sim40.truth()["reset_ns"] == 40.0
    assert 1.6 < n40 / n20 < 2.4
    _, m_off, _, _ = peak(dataclasses.replace(base, reset_offset_ps=600.0))
    assert 2.0 < m_off - m20 < 4.0  # 600 ps is ~3 codes
    _, _, s_wide, _ = peak(dataclasses.replace(base, reset_jitter_ps=300.0))
    assert s_wide > 1.3 * s20


def test_second_stage_in_time_is_flat_under_uniform_light():
    """``d2nd_in_time``: the second stage measures time in the VCO cycle, so uniform light
    fills its block evenly whatever the first stage's phase widths (the default mapping,
    (phase + frac) / 8, makes a narrow phase's eighth of the block sparse); Nth is the
    smallest D2nd at P1st = 0 and PDM (where phase 4 starts, in time) about that at
    P1st = 4."""
    spreads = []
    for in_time in (False, True):
        chip = make_chip(N, 3, inl_scale=1.3, d2nd_in_time=in_time, artifact_rate=0.0)
        words, sim = words_of(chip, scene(lux=401.849), 40_000)
        tdc, d1, d2 = hits_of(chip, words)
        x_t = chip.window_truth(sim.light, 80e-9)[1]
        keep = d1 < x_t[tdc] - 10  # away from the reset peak
        ratio = []
        for i in range(N):  # hits per eighth of the block, in fine order from Nth
            w = chip.width[i]
            mod = (d2[keep & (tdc == i)] - chip.n_th[i]) % w
            eighth = np.bincount(mod * 8 // w, minlength=8)
            ratio.append(eighth.min() / np.median(eighth))
        spreads.append(min(ratio))
        if in_time:
            p1 = d1 % 8
            for i in range(N):
                assert d2[(tdc == i) & (p1 == 0)].min() == chip.n_th[i]
                # PDM's truth is over every VCO cycle of the counter, some beyond x_T
                assert 0 <= d2[(tdc == i) & (p1 == 4)].min() - chip.pdm[i] <= 2
    assert spreads[0] < 0.65 < 0.75 < spreads[1]
