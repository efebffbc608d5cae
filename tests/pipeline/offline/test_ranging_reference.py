"""The range stage's faster path gives the results of the one it replaced, bit for bit,
but for two changes of arithmetic, each tested apart with its tolerance:

- the widths (``fwhm_s``): the compiled width sums each round's window only, its
  additions in another order than numpy's pairwise sums over whole rows, so a width may
  differ from the earlier one in its last bits (:data:`WIDTH_RTOL`, a million times below
  the photon noise of a width measured on even 10^6 counts, ~1e-3);
- the ML fit stops when a step moves its time and signal by less than
  :data:`stages.ranging.ml.STEP_TOL` of their own sigmas; with that tolerance 0 (the
  earlier rule: fixed points and the iteration limit only) the results are the earlier
  ones, and with it they move by a small part of their own sigmas (:data:`ML_SIGMAS`).

The reference below is the earlier code, kept here: the splines built at every call, one
median per TDC in ``light_end``, a calibration's TDC range built at every call, each
return's width computed on every pixel on fresh copies of the histograms. ``range_state``
run with those patched in is the earlier range stage.
"""

from __future__ import annotations

import dataclasses
import importlib

import numpy as np
import pytest

from pipeline.io.caldir import load_calibration
from pipeline.offline import ranging
from schemas.constants import N_CLASSES
from stages import calibration as cal
from stages.calibration_set import Calibration, time_axis
from stages.histogram import HistogramState
from stages.models.tcspc import FWHM_PER_SIGMA, SQRT2PI
from stages.ranging import multi
from stages.ranging.detection import _background
from stages.ranging.histograms import Histograms
from stages.ranging.width import ROUNDS, WINDOW_WIDTHS, return_sigma

# ------------------------------------------------------------------ the earlier code


def ref_spline_rows(levels, y, n, coord=np.sqrt):
    from scipy.interpolate import CubicSpline

    fin = np.isfinite(y)
    out = np.full(y.shape[0], np.nan)
    for pattern in np.unique(fin, axis=0):
        rows = np.all(fin == pattern, axis=1)
        lv = levels[pattern]
        if lv.size < 3:
            continue
        if not (pattern.all() or lv[0] - 1e-12 <= n <= lv[-1] + 1e-12):
            continue
        x = min(max(n, lv[0]), lv[-1])
        out[rows] = CubicSpline(coord(lv), y[rows][:, pattern].T, axis=0)(coord(x))
    return out


def ref_lsb_ps(self, n):
    n = np.asarray(n, np.float64)
    lv = None if self.levels is None else np.asarray(self.levels, np.float64)
    if lv is None or lv.size < 3 or n.ndim or not self.in_range(float(n)):
        return self.cubic_ps(n)
    order = np.argsort(lv)
    lv, y = lv[order], self.points_ps()[:, order]
    if not np.all(np.diff(lv) > 0):
        return self.cubic_ps(n)
    return ref_spline_rows(lv, y, float(n))


def ref_scale_at_light(density, lsb_s, window_s, fit=None, light=None, *_):
    bounds = cal.code_bounds(density)
    ok = np.asarray(density.ok, bool)
    if cal._interpolates(fit, light):
        levels, s_pts = cal.scale_points(density, fit, window_s)
        return np.where(ok, ref_spline_rows(levels, s_pts, float(light)), np.nan)
    x_t = window_s / np.asarray(lsb_s, np.float64)
    return np.where(ok, window_s / cal._bound_at(bounds, x_t), np.nan)


def ref_scale_spread(density, fit, window_s, light, *_):
    if not cal._interpolates(fit, light):
        return np.full(density.n_tdc, np.nan), (float("nan"), float("nan"))
    levels, s_pts = cal.scale_points(density, fit, window_s)
    in_sqrt = ref_spline_rows(levels, s_pts, float(light))
    in_n = ref_spline_rows(levels, s_pts, float(light), coord=lambda v: v)
    i = int(np.clip(np.searchsorted(levels, light, side="right") - 1, 0, levels.size - 2))
    return np.abs(in_n / in_sqrt - 1), (float(levels[i]), float(levels[i + 1]))


def ref_light_end(hits, min_per_code=1.0):
    h = np.asarray(hits)
    n = h.shape[1]
    populated = h.any(axis=1)
    top = np.where(populated, n - np.argmax(h[:, ::-1] > 0, axis=1), 0)
    k = np.arange(n)[None, :]
    below = (k >= top[:, None] - 40) & (k < top[:, None] - 10)
    level = np.array([np.median(row[b]) if b.any() else 0.0
                      for row, b in zip(h, below, strict=True)])
    return top, populated & (level >= min_per_code)


def ref_return_sigma(h, t_s, sigma0_s, rounds=ROUNDS):
    lam = h.intensity()
    w, valid = h.widths, np.asarray(h.valid, bool)
    bg = _background(lam, w, valid, h.at_risk)
    excess = np.where(valid, np.maximum(lam - bg[:, None] * w, 0.0), 0.0) * h.cycles[:, None]
    cen = h.centres
    t = np.asarray(t_s, np.float64).copy()
    sig = np.full(t.shape, max(float(sigma0_s), h.bin_s))
    tot = np.zeros(t.shape)
    for _ in range(rounds):
        half = WINDOW_WIDTHS * np.maximum(sig, h.bin_s)
        with np.errstate(invalid="ignore"):
            win = np.abs(cen - t[:, None]) <= half[:, None]
        e = np.where(win, excess, 0.0)
        tot = e.sum(axis=1)
        ok = tot > 0
        d = np.where(ok, tot, 1.0)
        mu = (e * cen).sum(axis=1) / d
        var = (e * (cen - mu[:, None]) ** 2).sum(axis=1) / d
        q = (e * w ** 2).sum(axis=1) / d / 12.0
        new = np.sqrt(np.maximum(var - q, 0.0))
        sig = np.where(ok & (new > 0), new, sig)
        t = np.where(ok, mu, t)
    bad = ~np.isfinite(np.asarray(t_s, np.float64)) | ~(tot > 0)
    return np.where(bad, np.nan, sig), np.where(bad, 0.0, tot)


def _ref_ml_kernel():
    """The ML fit's compiled loop as it was: every pixel through all its iterations, the
    normal CDF at the edges computed for the likelihood and again for the information."""
    import math

    from stages.ranging._numba import numba

    if numba is None:  # (the numpy path, unchanged)
        return None
    @numba.njit(cache=False, nogil=True)
    def ndtr(z):
        return 0.5 * math.erfc(-z / math.sqrt(2.0))

    @numba.njit(cache=False, nogil=True)
    def ml_ll(t0, m, bg, lo_e, hi_e, cnt, rr, ok, sigma_s):
        ll = 0.0
        for i in range(lo_e.size):
            if not ok[i]:
                continue
            dphi = ndtr((hi_e[i] - t0) / sigma_s) - ndtr((lo_e[i] - t0) / sigma_s)
            lam = max(m * dphi + bg * (hi_e[i] - lo_e[i]), 1e-300)
            ll += cnt[i] * math.log(-math.expm1(-lam)) - (rr[i] - cnt[i]) * lam
        return ll

    @numba.njit(cache=False, nogil=True)
    def ml_info(t0, m, bg, lo_e, hi_e, cnt, rr, ok, sigma_s):
        i00 = i01 = i11 = s0 = s1 = 0.0
        for i in range(lo_e.size):
            if not ok[i]:
                continue
            za = (lo_e[i] - t0) / sigma_s
            zb = (hi_e[i] - t0) / sigma_s
            dphi = ndtr(zb) - ndtr(za)
            lam = max(m * dphi + bg * (hi_e[i] - lo_e[i]), 1e-300)
            em1 = math.expm1(lam)
            sl = cnt[i] / em1 - (rr[i] - cnt[i])
            il = rr[i] / em1
            pdf = (math.exp(-0.5 * zb * zb) - math.exp(-0.5 * za * za)) / (SQRT2PI * sigma_s)
            jt = -m * pdf
            jm = dphi
            i00 += il * jt * jt
            i01 += il * jt * jm
            i11 += il * jm * jm
            s0 += sl * jt
            s1 += sl * jm
        return i00, i01, i11, s0, s1

    @numba.njit(cache=False, nogil=True)
    def kernel(counts_all, widths, centres, valid_all, cycles, t_start, peak, bg, k,
               sigma_s, iterations):
        n_pix, n = counts_all.shape
        nw = 2 * k + 1
        out_t, out_s, out_m = np.empty(n_pix), np.empty(n_pix), np.empty(n_pix)
        lo_e, hi_e, cnt, rr = np.empty(nw), np.empty(nw), np.empty(nw), np.empty(nw)
        ok = np.empty(nw, np.bool_)
        for p in range(n_pix):
            acc = 0.0
            cum = np.empty(n)
            for j in range(n):
                cum[j] = cycles[p] - acc
                acc += counts_all[p, j]
            last = -1
            hw = 0.0
            wsum = 0.0
            for i in range(nw):
                j = min(max(peak[p] - k + i, 0), n - 1)
                lo_e[i] = centres[p, j] - 0.5 * widths[p, j]
                hi_e[i] = centres[p, j] + 0.5 * widths[p, j]
                cnt[i] = counts_all[p, j]
                rr[i] = max(cum[j], 0.0)
                ok[i] = valid_all[p, j] and j != last
                last = j
                if ok[i]:
                    hw += cnt[i]
                    wsum += hi_e[i] - lo_e[i]
            r0 = max(rr[0], hw + 1)
            m = max(-math.log1p(-hw / r0) - bg[p] * wsum, 1e-9)
            t0 = t_start[p]
            ll = ml_ll(t0, m, bg[p], lo_e, hi_e, cnt, rr, ok, sigma_s)
            active = True
            for _ in range(iterations):
                if not active:
                    break
                i00, i01, i11, s0, s1 = ml_info(t0, m, bg[p], lo_e, hi_e, cnt, rr, ok,
                                                sigma_s)
                det = i00 * i11 - i01 * i01
                if det <= 0:
                    break
                st = (i11 * s0 - i01 * s1) / det
                sm = (i00 * s1 - i01 * s0) / det
                scale = 1.0
                better = False
                nt, nm, nll = t0, m, ll
                for _h in range(8):
                    nt = t0 + scale * st
                    nm = max(m + scale * sm, 1e-12)
                    nll = ml_ll(nt, nm, bg[p], lo_e, hi_e, cnt, rr, ok, sigma_s)
                    if nll >= ll - 1e-12:
                        better = True
                        break
                    scale *= 0.5
                if better:
                    t0, m, ll = nt, nm, nll
                if abs(scale * st) <= 1e-16:
                    active = False
            i00, i01, i11, _, _ = ml_info(t0, m, bg[p], lo_e, hi_e, cnt, rr, ok, sigma_s)
            det = i00 * i11 - i01 * i01
            out_t[p] = t0
            out_m[p] = m
            out_s[p] = math.sqrt(i11 / det) if det > 0 else np.inf
        return out_t, out_s, out_m, bg, peak

    return kernel


def ref_rows(h, rows, valid=None):
    return Histograms(h.counts[rows], h.edges_s[rows], h.cycles[rows],
                      h.valid[rows] if valid is None else valid)


def ref_calibration_rows(self, start, stop):
    return self._rows(start, stop)


@pytest.fixture(scope="module")
def ref_ml_kernel():
    return _ref_ml_kernel()


def patch_earlier(m, ml_kernel=None):
    """The earlier range stage, patched in (``m``: a monkeypatch; ``ml_kernel``: the ML
    fit's loop as it was, where numba is installed)."""
    if ml_kernel is not None:  # (the earlier loop had no step tolerance: fixed points only)
        m.setattr(importlib.import_module("stages.ranging.ml"), "_ml_numba",
                  lambda *a: ml_kernel(*a[:-1]))
    m.setattr(cal.LsbFit, "lsb_ps", ref_lsb_ps)
    m.setattr(cal, "scale_at_light", ref_scale_at_light)
    m.setattr(cal, "scale_spread", ref_scale_spread)
    m.setattr(cal, "light_end", ref_light_end)
    m.setattr(Calibration, "rows", ref_calibration_rows)
    m.setattr(multi, "_rows", ref_rows)
    m.setattr(multi, "return_fwhm",
              lambda h, t, s: FWHM_PER_SIGMA * ref_return_sigma(h, t, s)[0])


# ------------------------------------------------------------------ the measurements


def _state(hits, cycles, offset=0):
    hits = np.asarray(hits, np.uint64)
    cc = np.zeros((N_CLASSES, hits.shape[0]), np.uint64)
    cc[0] = hits.sum(1)
    cc[1] = cycles - cc[0]
    return HistogramState(hits, cc, int(cc.sum()), tdc_offset=offset)


@pytest.fixture(scope="module")
def measurements(mirror16):
    """The mirror at 1.5 m; it with a second, weaker return 40-70 codes lower on most
    TDCs (a window before the target) and a third on some; the second's TDCs 8-15 alone (a
    worker's range)."""
    st, _, window_s = mirror16
    rng = np.random.default_rng(7)
    cycles = int(st.cycles.max())
    hits = np.asarray(st.hits, np.float64)
    peak = np.argmax(hits[:, 20:-40], axis=1) + 20
    k = np.arange(hits.shape[1])[None, :]
    more = hits.copy()
    for shift, amp, rows in ((55, 300.0, slice(0, 14)), (110, 120.0, slice(0, 6))):
        c = np.clip(peak - shift, 15, None)[:, None]
        bump = np.zeros_like(hits)
        bump[rows] = amp * np.exp(-0.5 * ((k - c) / 1.6) ** 2)[rows]
        more = more + rng.poisson(bump)
    two = _state(more, cycles)
    part = _state(more[8:], cycles, offset=8)
    return [("mirror", st), ("returns", two), ("worker", part)], window_s


@pytest.fixture(scope="module")
def calibration(caldir):
    return load_calibration(caldir)


def _run(calib, state, window_s, **kw):
    est, d, s, note = ranging.range_state(state, calib, window_s, 140e-9, **kw)
    return {**{f: getattr(est, f) for f in ("t_s", "sigma_s", "fwhm_s", "signal_counts",
                                            "background_per_bin", "detected", "pixel",
                                            "return_index", "flag")},
            "distance": d, "sigma_m": s, "note": note}


#: how far a width summed over its window may be from the one summed over whole rows
#: (~1e-16 a sum, a few sums a round; measured <= 5e-16 on these measurements)
WIDTH_RTOL = 1e-12


#: how far the ML fit's stop at a step below STEP_TOL of its sigmas may move its time
#: (in the estimate's own sigma) and its signal and sigma (relative)
ML_SIGMAS, ML_RTOL = 0.01, 1e-3


def _same(a: dict, b: dict):
    assert a.keys() == b.keys()
    for k in a:
        x, y = a[k], b[k]
        if k == "fwhm_s":
            assert np.array_equal(np.isnan(x), np.isnan(y)), k
            np.testing.assert_allclose(x, y, rtol=WIDTH_RTOL, err_msg=k)
        elif isinstance(x, str):
            assert x == y, k
        elif np.asarray(x).dtype.kind == "f":
            assert np.array_equal(x, y, equal_nan=True), (k, x, y)
        else:
            assert np.array_equal(np.asarray(x), np.asarray(y)), (k, x, y)


@pytest.mark.parametrize("estimator", ["ml", "fast"])
def test_range_state_gives_the_earlier_results(measurements, calibration,
                                                           estimator, monkeypatch,
                                                           ref_ml_kernel):
    states, window_s = measurements
    cases = [(name, st, k, situ) for name, st in states for k in (1, 3)
             for situ in (False, True)]
    monkeypatch.setattr(importlib.import_module("stages.ranging.ml"), "STEP_TOL", 0.0)
    new = [_run(calibration, st, window_s, estimator=estimator, max_returns=k,
                in_situ=situ) for _, st, k, situ in cases]
    again = [_run(calibration, st, window_s, estimator=estimator, max_returns=k,
                  in_situ=situ) for _, st, k, situ in cases]  # (what was cached, reused)
    assert any((r["return_index"] > 0).any() for r in new)  # further returns were found
    assert any(np.isfinite(r["fwhm_s"][r["return_index"] > 0]).any() for r in new)
    fresh = Calibration(calibration.density, calibration.second, calibration.lsb_fit,
                        calibration.delay_s, calibration.delay_reasons,
                        calibration.irf_sigma_s, calibration.meta, calibration.path,
                        width_var_lsb2=calibration.width_var_lsb2)
    with monkeypatch.context() as m:
        patch_earlier(m, ref_ml_kernel)
        old = [_run(fresh, st, window_s, estimator=estimator, max_returns=k, in_situ=situ)
               for _, st, k, situ in cases]
    for a, b, c in zip(new, again, old, strict=True):
        _same(a, c)
        _same(b, c)


@pytest.mark.parametrize("situ", [False, True])
def test_the_ml_fits_step_tolerance_moves_it_by_a_small_part_of_its_sigma(
        measurements, calibration, monkeypatch, situ):
    """The ML fit's stop at a step below STEP_TOL of its sigmas against its stop at fixed
    points only: the same rows, detections and flags; times within ML_SIGMAS of their own
    sigma, the signal, sigma and width within ML_RTOL."""
    states, window_s = measurements
    ml_mod = importlib.import_module("stages.ranging.ml")
    assert ml_mod.STEP_TOL > 0
    for _, st in states:
        for k in (1, 3):
            now = _run(calibration, st, window_s, max_returns=k, in_situ=situ)
            with monkeypatch.context() as m:
                m.setattr(ml_mod, "STEP_TOL", 0.0)
                fixed = _run(calibration, st, window_s, max_returns=k, in_situ=situ)
            for name in ("pixel", "return_index", "detected", "flag"):
                assert np.array_equal(now[name], fixed[name]), name
            sig = fixed["sigma_s"]
            ok = np.isfinite(sig) & (sig > 0)
            assert np.all(np.abs(now["t_s"] - fixed["t_s"])[ok] <= ML_SIGMAS * sig[ok])
            for name in ("signal_counts", "sigma_s", "fwhm_s", "background_per_bin"):
                np.testing.assert_allclose(now[name], fixed[name], rtol=ML_RTOL, err_msg=name)


def test_without_an_lsb_fit_the_scale_is_the_earlier_one(measurements, calibration,
                                                         monkeypatch, ref_ml_kernel):
    """One density test (no LSB fit): the scale from the cached code boundaries."""
    states, window_s = measurements
    monkeypatch.setattr(importlib.import_module("stages.ranging.ml"), "STEP_TOL", 0.0)
    one = dataclasses.replace(calibration, lsb_fit=None)
    new = _run(one, states[1][1], window_s, max_returns=3)
    patch_earlier(monkeypatch, ref_ml_kernel)
    _same(new, _run(dataclasses.replace(one), states[1][1], window_s, max_returns=3))


def test_the_splines_read_at_any_light_are_the_ones_built_for_it(calibration):
    density, fit = calibration.density, calibration.lsb_fit
    levels, pts = cal.scale_points(density, fit, 80e-9)
    holes = pts.copy()
    holes[1, 0] = holes[2, -1] = holes[3, 1:3] = np.nan  # TDCs a test flagged
    lo, hi = levels[0], levels[-1]
    lights = [lo - 0.01, lo, np.sqrt(lo * hi), 0.5 * (levels[1] + levels[2]), hi,
              hi + 0.01, float(levels[2])]
    for y in (pts, holes):
        sqrt_, lin = cal.RowSplines(levels, y), cal.RowSplines(levels, y, lambda v: v)
        for n in lights:
            assert np.array_equal(sqrt_(n), ref_spline_rows(levels, y, n), equal_nan=True)
            assert np.array_equal(lin(n), ref_spline_rows(levels, y, n, lambda v: v),
                                  equal_nan=True)
    for n in lights:
        assert np.array_equal(fit.lsb_ps(n), ref_lsb_ps(fit, n), equal_nan=True)
        assert np.array_equal(fit.lsb_ps(n), ref_lsb_ps(fit, n), equal_nan=True)  # cached
        for a, b in zip(cal.scale_spread(density, fit, 80e-9, n,
                                         calibration.scale_splines(80e-9)),
                        ref_scale_spread(density, fit, 80e-9, n), strict=True):
            assert np.array_equal(a, b, equal_nan=True)
    assert calibration.rows(2, 9) is calibration.rows(2, 9)
    assert calibration.scale_splines(80e-9) is calibration.scale_splines(80e-9)


def test_light_end_gives_the_earlier_medians():
    """Every top a TDC's light may end at (the 30 codes below it whole, cut by code 0,
    none), and empty TDCs."""
    rng = np.random.default_rng(3)
    n = 512
    tops = np.r_[0, 1, 5, 10, 11, 12, 25, 39, 40, 41, 60, 200, 511, 512,
                 rng.integers(0, n + 1, 40)]
    hits = np.zeros((tops.size, n), np.uint64)
    for i, top in enumerate(tops):
        hits[i, :top] = rng.poisson(rng.choice([0.3, 1.0, 2.5, 40.0]), top)
        if top:
            hits[i, top - 1] = max(int(hits[i, top - 1]), 1)
    for h in (hits, hits.astype(np.float64), hits[:, ::-1]):
        top, step = cal.light_end(h)
        rtop, rstep = ref_light_end(h)
        assert np.array_equal(top, rtop) and np.array_equal(step, rstep)
    assert cal.light_end(hits)[1].any() and not cal.light_end(hits)[1].all()


def test_a_returns_width_on_the_pixels_that_have_it(measurements, calibration):
    """NaN times (no such return) skipped, the others as when every row was computed."""
    states, window_s = measurements
    st = states[1][1]
    ax = time_axis(calibration, st.hits, st.cycles, window_s)
    h = Histograms.from_codes(st.hits, ax.tau_edges_s, st.cycles, window_s, x_t=ax.x_t)
    t = np.asarray(h.centres[np.arange(h.counts.shape[0]),
                             np.argmax(np.where(h.valid, h.counts, -1), axis=1)])
    for tt in (t, np.where(np.arange(t.size) % 3 == 0, np.nan, t),
               np.full(t.size, np.nan)):
        for s0 in (h.bin_s, 3 * h.bin_s):
            a, b = return_sigma(h, tt, s0, compiled=False), ref_return_sigma(h, tt, s0)
            assert np.array_equal(a[0], b[0], equal_nan=True)  # numpy's: bit for bit
            assert np.array_equal(a[1], b[1])
            c = return_sigma(h, tt, s0)  # the compiled path, where numba is installed
            assert np.array_equal(np.isnan(c[0]), np.isnan(b[0]))
            np.testing.assert_allclose(c[0], b[0], rtol=WIDTH_RTOL)
            np.testing.assert_allclose(c[1], b[1], rtol=WIDTH_RTOL)
    masked = multi._rows(h, slice(None), multi._masked(h, [t], 1e-9))
    for name in ("at_risk", "widths", "centres", "bin_s"):
        assert np.array_equal(getattr(masked, name),
                              getattr(ref_rows(h, slice(None), masked.valid), name))


def test_the_range_stage_loads_its_kernels_at_start(caldir):
    """A fresh process: constructing the stage ranges a made-up measurement, so that the
    compiled kernels are loaded (numba's cache, ~0.25 CPU-seconds) before the first
    measurement arrives; nothing of it is counted as ranged."""
    import subprocess
    import sys

    from stages.ranging import numba

    if numba is None:
        pytest.skip("numba not installed")
    code = (
        "import sys\n"
        "from pipeline.io.caldir import load_calibration\n"
        "from pipeline.offline.ranging import RangeCore\n"
        "from stages.ranging import width\n"
        "ml = sys.modules['stages.ranging.ml']\n"
        "assert not ml._ml_numba.signatures and not width._sigma_numba.signatures\n"
        "core = RangeCore(load_calibration(sys.argv[1]), 'ml', max_returns=3)\n"
        "assert ml._ml_numba.signatures and width._sigma_numba.signatures\n"
        "assert core.ranged == 0 and core.notes == {}\n")
    res = subprocess.run([sys.executable, "-c", code, str(caldir)], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]


def test_without_numba_the_range_stage_gives_the_same_ranges(measurements, calibration,
                                                             caldir, tmp_path):
    """The numpy forms (numba not importable, a fresh process) range the measurement with
    several returns as the compiled path does: the same rows and detections, the times
    within ML_SIGMAS of their sigma, the widths within ML_RTOL."""
    import subprocess
    import sys

    states, window_s = measurements
    st = states[1][1]
    np.save(tmp_path / "hits.npy", np.asarray(st.hits))
    np.save(tmp_path / "classes.npy", np.asarray(st.class_counts))
    code = (
        "import sys\n"
        "sys.modules['numba'] = None  # (import numba fails: the numpy forms)\n"
        "import numpy as np\n"
        "from pipeline.io.caldir import load_calibration\n"
        "from pipeline.offline import ranging\n"
        "from stages.histogram import HistogramState\n"
        "from stages.ranging import numba\n"
        "assert numba is None\n"
        "d = sys.argv[2]\n"
        "h, c = np.load(d + '/hits.npy'), np.load(d + '/classes.npy')\n"
        "st = HistogramState(h, c, int(c.sum()))\n"
        "est, dist, s, note = ranging.range_state(st, load_calibration(sys.argv[1]),"
        " float(sys.argv[3]), 140e-9, max_returns=3)\n"
        "np.savez(d + '/out.npz', t=est.t_s, sig=est.sigma_s, fwhm=est.fwhm_s,"
        " det=est.detected, pixel=est.pixel, ri=est.return_index)\n")
    res = subprocess.run([sys.executable, "-c", code, str(caldir), str(tmp_path),
                          repr(window_s)], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    got = np.load(tmp_path / "out.npz")
    want = _run(calibration, st, window_s, max_returns=3)
    assert (want["return_index"] > 0).any()
    np.testing.assert_array_equal(got["pixel"], want["pixel"])
    np.testing.assert_array_equal(got["ri"], want["return_index"])
    np.testing.assert_array_equal(got["det"], want["detected"])
    ok = np.isfinite(want["sigma_s"])
    assert np.array_equal(np.isfinite(got["t"]), np.isfinite(want["t_s"]))
    assert np.all(np.abs(got["t"] - want["t_s"])[ok] <= ML_SIGMAS * want["sigma_s"][ok])
    np.testing.assert_allclose(got["fwhm"], want["fwhm_s"], rtol=ML_RTOL)


def test_the_range_stages_ranges_name_the_calibration_by_its_identity(measurements,
                                                                      calibration, tmp_path):
    """Issue 39: the daemon's ranges record the calibration's identity (its header, then
    the sink's parquet metadata), as `tcspc range`'s do."""
    import pyarrow.parquet as pq

    from pipeline.offline.ranging import RangeCore
    from pipeline.stream.stage import ParquetSink

    states, window_s = measurements
    core = RangeCore(calibration, "ml", forward_histograms=False)
    header = {"run": "r1", "measurement": "m1", "window_ns": window_s * 1e9,
              "t_laser_win_ns": 140.0, "date": "2026-12-05", "seq": 0}
    out = core.process(header, states[0][1].to_table("m1").to_batches()[0])
    head, batch = out[0]
    assert head["calibration_id"] == calibration.meta["calibration_id"] != ""
    sink = ParquetSink(tmp_path)
    sink.process(head, batch)
    (written,) = (tmp_path / "ranges").rglob("*.parquet")
    meta = pq.ParquetFile(written).schema_arrow.metadata
    assert meta[b"tcspc.calibration_id"].decode() == calibration.meta["calibration_id"]


def test_the_range_stage_tracks_the_lsb_for_the_campaigns_verdict(measurements, calibration,
                                                                  tmp_path):
    """Issue 39.3: the range stage's online LSB tracking (on the measurements it checks
    the chip on) goes in the ranges' header and the sink's parquet metadata, where the
    campaign's verdict reads it (flows.calibration.stream_drift_ps): the same chip under
    the same conditions has drifted by less than its own noise."""
    import json

    import pyarrow.parquet as pq

    from pipeline.offline.ranging import (
        CHIP_RECHECK,
        LSB_TRACK_AFTER_S,
        LSB_TRACK_EVERY_S,
        RangeCore,
    )
    from pipeline.stream.stage import ParquetSink

    states, window_s = measurements
    now = [0.0]
    core = RangeCore(calibration, "ml", forward_histograms=False, clock=lambda: now[0])
    header = {"run": "r1", "measurement": "m1", "window_ns": window_s * 1e9,
              "t_laser_win_ns": 140.0, "date": "2026-12-05", "seq": 0}
    hist = states[0][1].to_table("m1").to_batches()[0]
    # issue 38.9: not on the first measurement (its latency) nor more often than once
    # a minute (the stage's rate): the first tracking is LSB_TRACK_AFTER_S after the start
    ((head, _),) = core.process(header, hist)
    assert head["chip_check"] and "lsb_drift" not in head
    now[0] = LSB_TRACK_AFTER_S
    core._unchecked = CHIP_RECHECK  # (the next measurement is checked)
    ((head, batch),) = core.process(header, hist)
    drift = head["lsb_drift"]
    now[0] += LSB_TRACK_EVERY_S / 2
    core._unchecked = CHIP_RECHECK
    ((again, _),) = core.process(header, hist)
    assert again["chip_check"] and "lsb_drift" not in again  # (within the minute)
    assert drift["n"] > 0 and abs(drift["median_ps"]) < 4 * drift["se_ps"] + 1.0, drift
    ParquetSink(tmp_path).process(head, batch)
    (written,) = (tmp_path / "ranges").rglob("*.parquet")
    meta = pq.ParquetFile(written).schema_arrow.metadata
    assert json.loads(meta[b"tcspc.lsb_drift"]) == drift


def test_a_partial_measurements_ranges_are_flagged(measurements, calibration):
    """Issue 38.7: a measurement the run ended inside (the histogram worker's ``partial``)
    is ranged on what it holds, every row flagged as partial with the cycles it covers; a
    whole one is not."""
    from pipeline.offline.ranging import PARTIAL, RangeCore

    states, window_s = measurements
    core = RangeCore(calibration, "ml", forward_histograms=False, check_chip=False)
    header = {"run": "r1", "measurement": "m1", "window_ns": window_s * 1e9,
              "t_laser_win_ns": 140.0, "partial": True, "cycles": [20_000, 27_500]}
    batch = states[0][1].to_table("m1").to_batches()[0]
    ((_, cut),) = core.process(header, batch)
    assert all(f.startswith(PARTIAL) and "cycles 20000..27500" in f
               for f in cut.column("flag").to_pylist())
    ((_, whole),) = core.process({**header, "partial": False}, batch)
    assert not any(PARTIAL in f for f in whole.column("flag").to_pylist())
