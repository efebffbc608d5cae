"""Calibration campaigns on captures: density test, LSB against light, delay. Each result
is a :class:`stages.calibration_set.Calibration`, saved with its provenance by
``pipeline.io.caldir.save_calibration`` (atomically) and loaded once by
``load_calibration``."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.io.caldir import load_calibration, save_calibration
from pipeline.io.capture import Capture
from schemas.errors import CalibrationError
from stages import calibration as cal
from stages.calibration import uncertainty, zero_test
from stages.calibration_set import Calibration, time_axis
from stages.histogram import HistogramAccumulator


def over_finite(stat, values) -> float:
    """``stat`` over the finite values; NaN when there is none (every TDC flagged), said
    by the value rather than by a numpy warning."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    return float(stat(v)) if v.size else float("nan")


def second_stage_counts(capture: Capture, progress=None) -> np.ndarray:
    """A capture's joint counts of (TDC, P1st, D2nd) over hit candidates (one pass)."""
    ss = cal.SecondStageAccumulator(capture.meta.n_tdc)
    for first, words in capture.iter_chunks():
        ss.update(words, first)
        if progress:
            progress(words.size)
    return ss.counts


def density_histograms(capture: Capture, progress=None,
                       second: cal.SecondStage | None = None):
    """A uniform-light capture's D1st histograms (artifact words apart, by code) and
    second-stage parameters: two passes, the second stage's bounds first. ``second``:
    the bounds to filter with (a campaign's, :func:`campaign_histograms`): one pass."""
    if second is None:
        second = cal.second_stage_params(second_stage_counts(capture, progress))
    acc = HistogramAccumulator(capture.meta.n_tdc, second.bounds, count_artifacts=True)
    for first, words in capture.iter_chunks():
        acc.update(words, first)
        if progress:
            progress(words.size)
    return acc.snapshot(), second


def campaign_histograms(captures: list, progress=None) -> list:
    """:func:`density_histograms` of several density tests of one chip, all filtered with
    one set of bounds (:func:`stages.calibration.campaign_second_stage`: the bounds are the
    chip's, and the brightest test shows them most clearly). Returns ``(state, second)``
    pairs, ``second`` the same for every test."""
    joints = [second_stage_counts(c, progress) for c in captures]
    second = cal.campaign_second_stage(joints, [getattr(c.meta, "cycles", 1)
                                                for c in captures])
    return [density_histograms(c, progress, second) for c in captures]


def checked(state, res: cal.DensityResult, second: cal.SecondStage) -> cal.DensityResult:
    """``res`` with the TDCs flagged whose artifact bounds cannot be trusted (their hits
    may hold artifact words) or whose reset peak is not where the window ends."""
    res = res.flagged(second.uncertain, [f"artifact bounds uncertain: {r}"
                                         for r in second.reasons] or "")
    why = cal.implausible_reset_peak(state.hits, res)
    return res.flagged(why != "", why.tolist())


def refilled(state, res: cal.DensityResult, others: list, window_s: float,
             combine: bool = False):
    """``res`` (of histograms ``state``) again, with the codes under its reset peak taking
    the widths that ``others`` (``(state, result)`` pairs of density tests at other light)
    measured there, each weighted against the phase mean by its error; with ``combine``,
    every code takes the inverse-variance mean of all the tests' widths."""
    tests = [(r, cal.width_variance(st.hits, st.cycles, r, st.artifacts)) for st, r in others]
    return cal.density_test(state.hits, state.cycles, window_s,
                            fill=cal.fill_from(tests, res), artifacts=state.artifacts,
                            combine=combine)


def density_from_capture(capture: Capture, inl_rms_lsb: float | None = 0.3,
                         progress=None, fill: list | tuple = (), variance: dict | None = None
                         ) -> tuple[cal.DensityResult, cal.SecondStage]:
    """Run a density test on a uniform-light capture (two passes: second stage, then D1st).

    ``fill``: captures of density tests at other light (dimmer: their reset peaks ~10
    codes higher at half the light) that measure the codes under this one's reset peak
    (see :func:`refilled`). Raises CalibrationError when the capture is too small for
    ``inl_rms_lsb`` (None: no check), saying how many cycles are needed. ``variance``: a
    dict that receives ``"width_var"`` (:func:`table_variance`), for :func:`write_caldir`.
    """
    # one set of bounds for this test and its fills (the chip's, campaign_second_stage)
    (state, second), *rest = campaign_histograms([capture, *fill], progress)
    window_s = capture.meta.window_ns * 1e-9
    own = res = checked(state, cal.density_test(state.hits, state.cycles, window_s,
                                                artifacts=state.artifacts), second)
    others = []
    if fill:
        others = [(st, checked(st, cal.density_test(st.hits, st.cycles, window_s,
                                                    artifacts=st.artifacts), second))
                  for st, _ in rest]
        res = refilled(state, res, others, window_s)
        res = checked(state, res, second)
        res = cal.continue_table(res, [r for _, r in others])
    if variance is not None:
        variance["width_var"] = table_variance(state, own, others, res)
    if inl_rms_lsb is not None:
        worst = np.nanmax(np.where(res.ok, res.inl_error_lsb, np.nan)) if res.ok.any() else np.inf
        if not np.isfinite(worst) or worst > inl_rms_lsb:
            rate = float(np.nanmedian(np.where(res.ok, res.detections_per_cycle, np.nan))) \
                if res.ok.any() else 0.25
            need = cal.cycles_needed(inl_rms_lsb, starts_per_cycle=max(rate, 1e-6))
            raise CalibrationError(
                f"{capture.bin_path}: {capture.meta.cycles} cycles give an INL error of "
                f"{worst:.2f} LSB RMS; {inl_rms_lsb} LSB needs about {need:,} cycles at this "
                f"light level ({rate:.1%} STARTs per cycle)")
    return res, second


def write_caldir(out: str | Path, density: cal.DensityResult, second: cal.SecondStage,
                 sources: list[Path], lsb_fit: cal.LsbFit | None = None,
                 extra: dict | None = None, width_var=None) -> Path:
    """A new calibration (a density test, and the LSB against light where fitted, no delay
    yet) saved to ``out`` atomically (a failure leaves the old one in place).
    ``width_var``: the variance of every code width (:func:`table_variance`)."""
    calibration = Calibration(density, second, lsb_fit, np.full(density.n_tdc, np.nan), (),
                              None, dict(extra or {}), width_var_lsb2=width_var)
    return save_calibration(calibration, out, sources)


def lsb_campaign(captures: list, out: str | Path, inl_rms_lsb: float = 0.5,
                 log=None) -> tuple[cal.DensityResult, cal.LsbFit, np.ndarray, np.ndarray]:
    """Density tests at several light levels -> LSB per TDC as a cubic in eq. 5.1's n, INL
    from the test with the smallest statistical error; written to ``out`` atomically.
    ``captures``: capture paths, or objects read like one (a daemon's journal run).

    The codes under that test's own reset peak, which it cannot measure, take the widths
    the other tests measured there (each at another light, so with its reset peak
    elsewhere), weighted against the phase mean by their errors (``density_test(fill=)``).

    Returns the density test kept for the INL, the fit, the light levels and the per-test
    LSBs (ps, TDC x test). Raises CalibrationError when no test reaches ``inl_rms_lsb``.
    """
    caps = [path if hasattr(path, "iter_chunks") else Capture(path) for path in captures]
    # one set of artifact bounds for all the tests (the chip's): a dim test alone can take
    # a strong artifact for part of the block; dim tests give an LSB, not an INL
    tests = campaign_histograms(caps)
    window_s = caps[0].meta.window_ns * 1e-9
    var: dict = {}
    best, second, fit, n, lsbs, i_best = lsb_from_states(
        tests, window_s, inl_rms_lsb, names=[c.bin_path.name for c in caps], log=log,
        variance=var)
    sources = [p for c in caps for p in getattr(c, "paths", [c.bin_path])]
    write_caldir(out, best, second, sources, lsb_fit=fit, width_var=var.get("width_var"))
    return best, fit, n, lsbs


def table_variance(state, own: cal.DensityResult, others: list,
                   final: cal.DensityResult) -> np.ndarray:
    """(n_tdc, 512) variance (LSB^2) of every code width of ``final`` (the kept test
    ``own``, of histograms ``state``, filled and combined from ``others`` as
    :func:`refilled` does): each test's counting (:func:`stages.calibration.width_variance`)
    combined by inverse variance; the codes no test measured take the random DNL's
    variance about the phase pattern (:func:`stages.calibration.uncertainty.table_var`)."""
    mine = cal.width_variance(state.hits, state.cycles, own, state.artifacts)
    tests = [(r, cal.width_variance(st.hits, st.cycles, r, st.artifacts)) for st, r in others]
    fill = cal.fill_from(tests, own)[1] if tests else None
    var = uncertainty.table_var(final.width_lsb, mine, fill)
    return np.where(np.asarray(final.ok, bool)[:, None], var, np.nan)


def lsb_from_states(tests: list, window_s: float, inl_rms_lsb: float = 0.5,
                    names: list[str] | None = None, log=None, combine: bool = True,
                    variance: dict | None = None):
    """:func:`lsb_campaign` on histograms: ``tests`` a list of ``(state, second)`` pairs
    (:func:`density_histograms` of each density test). Returns ``(density, second, fit,
    n, lsbs, i_best)``: the density test kept for the INL (filled from the others), its
    second stage, the LSB fit, the light levels, the per-test LSBs (ps, TDC x test) and
    the index of the test kept. With ``combine`` (the default) every code's width is the
    inverse-variance mean over all the tests that measured it (the DNL does not change
    with light), not only the codes under the kept test's reset peak: the INL error
    falls by about sqrt(all hits / its hits) (0.100 -> 0.052 LSB RMS over six tests in
    ``benchmarks/range_accuracy.py``), and beyond the kept test's window the table goes
    on over the codes dimmer tests measured (the time axis at their light reads x_T
    there). ``variance``: a dict that receives ``"width_var"``, the variance of every code
    width of the density test returned (:func:`table_variance`), for
    :func:`write_caldir`."""
    names = names or [f"test {i}" for i in range(len(tests))]
    results = []
    for name, (state, second) in zip(names, tests, strict=True):
        res = checked(state, cal.density_test(state.hits, state.cycles, window_s,
                                              artifacts=state.artifacts), second)
        results.append(res)
        lost = np.flatnonzero(cal.phase_depleted(state.hits))
        if log and lost.size:
            log(f"{name}: TDCs {lost.tolist()} flagged: a phase (code mod 8) without its "
                f"share of the light (words lost, e.g. by wrong artifact bounds)")
        if log:
            log(f"{name}: {over_finite(np.mean, res.detections_per_cycle):.3f} STARTs per "
                f"pixel per cycle, LSB {over_finite(np.mean, res.lsb_s) * 1e12:.2f} ps (mean "
                f"of {np.isfinite(res.lsb_s).sum()} TDCs)")
    # a test's LSB far from the other tests' (the LSB moves by tens of ps with light, not
    # by half) is not the chip's: flagged, and then the TDC has no LSB fit
    lsbs = np.column_stack([r.lsb_s * 1e12 for r in results])
    for i, r in enumerate(results):
        others = np.delete(lsbs, i, axis=1)
        mid = np.full(r.n_tdc, np.nan)
        has = np.isfinite(others).any(axis=1)
        mid[has] = np.nanmedian(others[has], axis=1)
        off = np.abs(lsbs[:, i] / mid - 1) > LSB_SPREAD  # NaN: False
        results[i] = r.flagged(off, [f"{names[i]}: LSB {a:.0f} ps, the other tests' "
                                     f"{b:.0f} ps" for a, b in zip(lsbs[:, i], mid, strict=True)])
    # the light over the TDCs the test calibrated (one with words lost is no measure of
    # it); over all of them where it calibrated none (too dim: the fit still has a level)
    n = np.array([over_finite(np.mean, np.where(r.ok, r.detections_per_cycle, np.nan))
                  if r.ok.any() else over_finite(np.mean, r.detections_per_cycle)
                  for r in results])
    lsbs = np.column_stack([r.lsb_s * 1e12 for r in results])
    fit = cal.fit_lsb(n, lsbs)
    # each point's own error: its x_T's (the reset peak fit) and its counted light's
    # (binomial over the TDC-cycles that count it, as `n` does)
    used = [np.where(r.ok, 1.0, 0.0) if r.ok.any() else np.ones(r.n_tdc) for r in results]
    tdc_cycles = np.array([float(np.sum(u * np.max(st.cycles))) for u, (st, _) in
                           zip(used, tests, strict=True)])
    fit = dataclasses.replace(fit, sigma_ps=cal.point_sigma_ps(
        fit, lsbs, np.column_stack([r.x_t for r in results]),
        np.column_stack([np.full(r.n_tdc, np.nan) if r.x_t_var is None else r.x_t_var
                         for r in results]),
        n * (1 - n) / np.maximum(tdc_cycles, 1.0)))
    # a TDC flagged in any test has no LSB against light: flagged in the result kept
    why = [next((f"{nm}: {r.reasons[t]}" for nm, r in zip(names, results, strict=True)
                 if not r.ok[t]), "") for t in range(lsbs.shape[0])]
    no_fit = ~np.all(np.isfinite(fit.coef), axis=1)

    def worst_inl(r: cal.DensityResult) -> float:  # inf when no TDC was calibrated
        e = r.inl_error_lsb[r.ok]
        return float(np.nanmax(e)) if np.isfinite(e).any() else float("inf")

    # first the test that calibrated the most TDCs (one can flag TDCs the others
    # calibrated: cal.phase_depleted), then the smallest error
    i_best = min(range(len(results)), key=lambda i: (-int(results[i].ok.sum()),
                                                     worst_inl(results[i])))
    best = results[i_best]
    others = [(tests[i][0], r) for i, r in enumerate(results) if i != i_best]
    if others:
        best = refilled(tests[i_best][0], best, others, window_s, combine)
        best = checked(tests[i_best][0], best, tests[i_best][1])
        # the codes under the dimmest test's reset peak, measured by none, as it put them
        best = cal.continue_table(best, [r for _, r in others])
        if log:
            log(f"INL from {names[i_best]}; the codes under its reset peak also "
                f"from the {len(others)} other test(s)")
    best = best.flagged(no_fit, [w or "no LSB in some density test" for w in why])
    if variance is not None:
        variance["width_var"] = table_variance(tests[i_best][0], results[i_best], others, best)
    if log and not best.ok.all():
        log(f"{int((~best.ok).sum())} TDC(s) flagged: " + "; ".join(
            f"{t}: {best.reasons[t]}" for t in np.flatnonzero(~best.ok)[:8]))
    if not best.ok.any():
        raise CalibrationError(
            f"no TDC calibrated (the best density test: {names[i_best]}): " + "; ".join(
                f"{t}: {best.reasons[t] or 'no reason given'}" for t in range(min(4, best.n_tdc))))
    if log and fit.levels is not None:
        # where the levels leave the LSB against light unresolved (cal.scale_spread): a
        # delay or range at that light is flagged unless its own reset peak scales it
        lv = np.sort(np.asarray(fit.levels, np.float64))
        for a, b in zip(lv[:-1], lv[1:], strict=True):
            mid = float(np.sqrt(a * b))
            worst_ppm = over_finite(np.max, cal.scale_spread(best, fit, window_s, mid)[0]) * 1e6
            log(f"LSB between the levels {a:.3g} and {b:.3g}: the sqrt(n) and n "
                f"interpolations differ by up to {worst_ppm:.0f} ppm of the scale at "
                f"{mid:.3g} ({worst_ppm * window_s * 1e6:.0f} ps at the window's beginning)"
                + ("; add a density test there" if worst_ppm * window_s * 1e6 > 100 else ""))
    worst = worst_inl(best)
    if not worst <= inl_rms_lsb:
        raise CalibrationError(f"the best density test ({names[i_best]}) gives an "
                               f"INL error of {worst:.2f} LSB RMS > {inl_rms_lsb}")
    return best, tests[i_best][1], fit, n, lsbs, i_best


#: How far (relative) a density test's LSB may be from the median of the other tests'
#: before it is taken for a misplaced reset peak: the LSB moves with light by up to ~50 ps
#: on ~220 (the zoo's fastest saturating chips), +-12 % about the middle test.
LSB_SPREAD = 0.3

#: What a delay measurement needs: return counts, and codes between the return and the
#: masked reset peak or window end, in instrument-response sigmas.
DELAY_MIN_COUNTS, DELAY_CLEAR_SIGMAS = 20, 3.0
RESET_MASK = 6  #: codes below x_T masked by the estimators (Histograms.from_codes margin)


def add_delay(capture, caldir: str | Path, log=None, distance_m: float = 0.0) -> Calibration:
    """Measure the system delay per TDC on a zero-distance capture (eq. 5.3), or on one of
    a target at a known ``distance_m`` (its round trip taken off), and rewrite ``caldir``
    with it (atomically). Returns the calibration as written (its ``delay_s``
    in seconds, NaN where there is none, and ``delay_reasons``).

    The peak's tau is the range stage's: the pile-up-exact ML on the calibrated time axis
    (so a target at zero distance ranges to zero). The axis's scale at the capture's light
    comes from the LSB polynomial, or from the capture's own reset peak where that is
    trustworthy: found where its uniform light ends, on codes the density test measured,
    with the return (located first on the polynomial's axis) well clear of it
    (:func:`stages.calibration_set.time_axis`); the source of each TDC's scale, and why
    the reset peak was declined, are recorded. A TDC without a delay gets the reason in
    ``meta.json`` (``delay.reasons``). Raises CalibrationError, leaving ``caldir`` as it
    was, when no TDC got a delay.
    """
    cap = capture if hasattr(capture, "iter_chunks") else Capture(capture)
    calib = load_calibration(caldir)
    if calib.n_tdc != cap.meta.n_tdc:
        raise CalibrationError(f"{caldir}: calibrates {calib.n_tdc} TDCs, {cap.bin_path} has "
                               f"{cap.meta.n_tdc}")
    acc = HistogramAccumulator(cap.meta.n_tdc, calib.bounds, count_artifacts=True)
    for first, words in cap.iter_chunks():
        acc.update(words, first)
    calib = delay_from_state(calib, acc.snapshot(), cap.meta.window_ns * 1e-9,
                             cap.meta.t_laser_win_ns * 1e-9, str(cap.bin_path), log,
                             distance_m)
    sources = [Path(s["path"]) for s in calib.meta.get("sources", []) if Path(s["path"]).exists()]
    save_calibration(calib, caldir, sources + getattr(cap, "paths", [cap.bin_path]))
    return calib


def delay_from_state(calib: Calibration, state, window_s: float, t_laser_win_s: float,
                     name: str = "capture", log=None, distance_m: float = 0.0
                     ) -> Calibration:
    """:func:`add_delay` on a zero-distance (or ``distance_m``) capture's histograms
    (``state``, a :class:`stages.histogram.HistogramState`): the calibration with the
    delay, not saved. Raises CalibrationError when no TDC got a delay."""
    from scipy.constants import c as c_light

    from stages.ranging import Histograms, ml

    light = cal.light_level(state.hits, state.cycles)  # eq. 5.1

    def estimate(axis):
        irf = cal.histogram_sigma_s(state.hits, calib.density, axis.scale)
        irf = irf[np.isfinite(irf) & (irf > 0)]  # an empty histogram's width is 0
        widths = np.diff(axis.tau_edges_s, axis=1)
        # the instrument response; 1 LSB where no TDC's peak says (as the range stage)
        sigma = float(np.median(irf)) if irf.size else \
            float(np.nanmedian(widths)) if np.isfinite(widths).any() else 200e-12
        h = Histograms.from_codes(state.hits, axis.tau_edges_s, state.cycles, window_s,
                                  x_t=axis.x_t)
        return ml(h, sigma), sigma

    def code_of(t_s, tau_edges, keep):
        return np.array([np.interp(window_s - t, e, np.arange(e.size, dtype=np.float64))
                         if k and np.isfinite(t) and np.all(np.isfinite(e)) else np.nan
                         for t, e, k in zip(t_s, tau_edges, keep, strict=True)])

    # the return first on the polynomial's axis, so the reset peak's fit can keep clear of it
    axis = time_axis(calib, state.hits, state.cycles, window_s)
    first, first_sigma = estimate(axis)
    returns = code_of(first.t_s, axis.tau_edges_s, first.detected)
    # the capture's own uniform light, clear of its return and reset peak, measures the
    # table's codes too: above the brightest density test's window, those the delay sums
    if ZERO_AS_TEST:
        calib = with_zero_density(calib, state, window_s, returns, first_sigma, axis, name,
                                  log)
        axis = time_axis(calib, state.hits, state.cycles, window_s)
    res = calib.density
    # where the levels leave the scale at this light unresolved (below), the capture's own
    # reset peak may sit on codes only the dimmer density tests measured: it follows
    # the chip there instead of the spline
    spread, (lo, hi) = cal.scale_spread(res, calib.lsb_fit, window_s, light)
    weak = cal.scale_unresolved(spread, window_s - np.asarray(first.t_s, np.float64), res,
                          first.sigma_s)
    axis = time_axis(calib, state.hits, state.cycles, window_s, in_situ=True, returns=returns,
                     beyond=weak if weak.any() else None)
    est, sigma = estimate(axis)
    if not (np.isfinite(distance_m) and distance_m >= 0):
        raise CalibrationError(f"--distance-m must be >= 0, found {distance_m}")
    # eq. 5.3 with the target at distance_m: eq. 5.4 then ranges this capture to it
    d = cal.delay_s(t_laser_win_s, window_s - est.t_s) - 2 * distance_m / c_light
    # where the return sits: a return partly under the reset peak's mask or at the window's
    # end is biased (fit on one flank), one with a handful of counts is no measurement
    widths = np.diff(axis.tau_edges_s, axis=1)
    has = np.isfinite(widths).any(axis=1)  # a TDC without a time axis has no width
    lsb = np.full(state.n_tdc, np.nan)
    lsb[has] = np.nanmedian(widths[has], axis=1)
    at = code_of(est.t_s, axis.tau_edges_s, np.ones(state.n_tdc, bool))
    reach = DELAY_CLEAR_SIGMAS * sigma / lsb  # codes the return spreads over, each side
    reasons = np.full(state.n_tdc, "", dtype=object)
    reasons[~np.isfinite(d)] = "no peak position (estimator gave none)"
    reasons[at < 1 + reach] = ("return at the window's end (partly cut off): move the gate "
                               "(T_laser-win) later")
    reasons[at > np.floor(axis.x_t) - RESET_MASK - reach] = (
        "return within reach of the reset peak (partly masked): move the gate "
        "(T_laser-win) earlier")
    reasons[np.asarray(est.signal_counts, np.float64) < DELAY_MIN_COUNTS] = (
        f"under {DELAY_MIN_COUNTS} return counts (a return under the reset peak, or too "
        "dim)")
    # (a return under the reset peak's mask is not detected on the valid bins beside it:
    # where it sits is the reason where its counts say a return is there)
    reasons[~np.asarray(est.detected, bool) & ~(
        (at > np.floor(axis.x_t) - RESET_MASK - reach)
        & (np.asarray(est.signal_counts, np.float64) >= DELAY_MIN_COUNTS))] = (
        "no return detected at the false-alarm rate")
    # the polynomial away from the light it was fitted at is a guess (0.7 ns of delay at
    # 0.8 detections a cycle on a fit over 0.02-0.69): only the capture's reset peak helps
    if axis.note:
        guess = (axis.source != "reset peak") & (reasons == "")
        reasons[guess] = [f"{axis.note}, and the capture's own reset peak not usable "
                          f"({str(src).split(': ', 1)[-1]}): run `tcspc calibrate lsb` "
                          "over this light" for src in axis.source[guess]]
    # between the density tests' levels the scale is a spline through their points: where
    # the LSB bends faster than the levels show (a fast-saturating chip) it can be off by
    # more than the delay allows with nothing to see in four points (issue 15); two
    # interpolations through the same points then part, and only the capture's own reset
    # peak measures the scale there
    tau_s = window_s - np.asarray(est.t_s, np.float64)
    spread_ps = spread * tau_s * 1e12
    unresolved = ((axis.source != "reset peak") & (reasons == "")
                  & cal.scale_unresolved(spread, tau_s, res, est.sigma_s))
    reasons[unresolved] = (
        f"LSB against light not resolved between the density tests at {lo:.3g} and "
        f"{hi:.3g} detections a cycle (two interpolations through them differ by more than "
        f"the delay's error allows here): add a density test near {light:.2g} to `tcspc "
        "calibrate lsb`, or give this capture ambient light (its own reset peak then "
        "scales it)")
    reasons[state.hits.sum(axis=1) == 0] = "no hits in the capture"
    bad = ~calib.ok
    reasons[bad] = ["flagged by the density test" + (f": {r}" if r else "")
                    for r in np.asarray(calib.density.reasons, dtype=object)[bad]]
    d = np.where(reasons == "", d, np.nan)
    if not np.isfinite(d).any():
        counts = {r: int(np.sum(reasons == r)) for r in sorted(set(reasons.tolist()))}
        raise CalibrationError(f"{name}: no TDC got a delay ({counts}); the calibration "
                               "is left as it was")
    source = axis.source
    if log:
        log(f"return found on the polynomial's axis on {int(np.isfinite(returns).sum())} of "
            f"{state.n_tdc} TDCs; time axis from the capture's reset peak on "
            f"{int(np.sum(source == 'reset peak'))}")
    calib = calib.with_delay(d, reasons.tolist(), sigma, {
        "capture": name, "light": light, "distance_m": distance_m,
        "counts_used": np.round(est.signal_counts).tolist(),
        "sigma_ps": np.round(est.sigma_s * 1e12, 3).tolist(),
        "scale_from": source.tolist(),
        "scale_from_reset_peak": int(np.sum(source == "reset peak")),
        "lsb_spread_ps": [None if not np.isfinite(v) else round(float(v), 1)
                          for v in np.where(source == "reset peak", np.nan, spread_ps)],
        "tdcs_with_delay": int(np.isfinite(d).sum()),
        **delay_uncertainty(calib, at, axis, est.sigma_s, spread, d,
                            calib.scale_refs(window_s, light, axis.source))})
    return calib


#: Whether ``calibrate delay`` counts the zero capture's uniform light as one more density
#: test (:mod:`stages.calibration.zero_test`; issue 33: on the issue's captures the delay's
#: counting floor 74.0 -> 68.8 ps RMS, the chain's error 68.7 -> 62.7 on zoo seeds 1-3 and
#: 81.1 -> 75.5 on 6-8, paired; docs/calibration.md).
ZERO_AS_TEST = True


def with_zero_density(calib: Calibration, state, window_s: float, returns, sigma_s: float,
                      axis, name: str = "capture", log=None) -> Calibration:
    """``calib`` with the zero capture's code widths (histograms ``state``) combined into
    its table by inverse variance (:func:`stages.calibration.zero_test.with_test`): its
    return (at the codes ``returns``, NaN where none was located) masked over
    ``ZERO_CLEAR_SIGMAS`` response sigmas (``sigma_s`` on ``axis``) and its reset peak
    left as a density test leaves it. The same capture is not counted twice (meta.json's
    ``zero_density`` lists the captures counted: name, counts, the SHA-256 of their
    histograms; another zero capture adds its own); a calibration without a table
    variance (made before issue 33.3) is returned as it was."""
    import hashlib

    h = np.asarray(state.hits)
    # the histograms' digest: the same counts under another name are the same capture
    digest = hashlib.sha256(np.ascontiguousarray(h, np.uint64).tobytes()).hexdigest()
    mark = {"capture": name, "hits": int(h.sum()),
            "cycles": int(np.max(np.asarray(state.cycles))), "sha256": digest}
    done = calib.meta.get("zero_density", [])
    if calib.width_var_lsb2 is None or any(d.get("sha256") == digest for d in done):
        if log and calib.width_var_lsb2 is not None:
            log(f"{name}: its uniform light is already in the table (not counted twice)")
        return calib
    widths = np.diff(axis.tau_edges_s, axis=1)
    with np.errstate(invalid="ignore"):
        lsb = np.array([np.nanmedian(w) if np.isfinite(w).any() else np.nan for w in widths])
    mask = zero_test.return_mask(returns, sigma_s / lsb)
    zres, zvar = zero_test.zero_density(h, state.cycles, window_s, mask, state.artifacts)
    density, var, used = zero_test.with_test(calib.density, calib.width_var_lsb2, zres, zvar)
    if not used.any():
        return calib
    if log:
        log(f"{name}: its uniform light (the return masked) measured "
            f"{int(np.median(used[used > 0]))} codes of the table (median) on "
            f"{int((used > 0).sum())} of {calib.n_tdc} TDCs")
    meta = {**calib.meta, "zero_density": [*done, {
        **mark, "codes_used": used.tolist(), "return_mask_sigmas": zero_test.ZERO_CLEAR_SIGMAS}]}
    return dataclasses.replace(calib, density=density, width_var_lsb2=var, meta=meta)


def _listed(v, digits: int) -> list:
    return [None if not np.isfinite(x) else round(float(x), digits)
            for x in np.asarray(v, np.float64)]


def delay_uncertainty(calib: Calibration, at, axis, peak_sigma_s, spread, delay,
                      refs=None) -> dict:
    """The delay's standard error per TDC (issue 33.3), for meta.json's ``delay``: the
    zero capture's peak (its fit's sigma), the table's counting noise over the codes the
    delay spans (:func:`stages.calibration.uncertainty.table_sigma_s` at the return's
    code ``at`` on the capture's ``axis``) and the time scale's (the LSB interpolation's
    spread where the axis is the polynomial's), in quadrature; with what a range needs to
    take the codes it shares with the delay together (``uncertainty``). ``refs``: where
    the scale is the density tests' interpolated (:meth:`Calibration.scale_refs`), the
    table's error at their x_T."""
    tau = np.asarray(axis.scale, np.float64) * _bound_at_codes(calib, at)
    rel = np.where(np.asarray(axis.source) == "reset peak", 0.0,
                   uncertainty.scale_rel_sigma(spread))
    if calib.width_var_lsb2 is None:
        table = np.zeros(calib.n_tdc)
    else:
        table = uncertainty.table_sigma_s(calib.width_var_lsb2, at, axis.x_t, axis.scale, refs)
    total = np.sqrt(np.asarray(peak_sigma_s, np.float64) ** 2 + table ** 2 + (rel * tau) ** 2)
    total = np.where(np.isfinite(delay), total, np.nan)
    return {"delay_sigma_ps": _listed(total * 1e12, 3),
            "uncertainty": {"return_code": _listed(at, 4), "x_t": _listed(axis.x_t, 4),
                            "scale_s": _listed(axis.scale, 18),
                            "scale_rel_sigma": _listed(rel, 9),
                            "table_sigma_ps": _listed(table * 1e12, 3),
                            "from_table": calib.width_var_lsb2 is not None}}


def _bound_at_codes(calib: Calibration, x) -> np.ndarray:
    """The table's boundary (its units) at fractional codes ``x`` (NaN stays NaN)."""
    return cal._bound_at(calib.code_bounds, x)


@dataclass(frozen=True)
class Quality:
    """What makes one calibration better than another: more TDCs calibrated, a smaller
    statistical INL error, a smaller LSB-fit residual, a measured delay."""

    tdcs_ok: int
    inl_error_lsb: float      #: median over calibrated TDCs
    lsb_residual_ps: float    #: RMS of the LSB fit's residuals (NaN with <= 4 levels: a
    #: cubic through 4 points has none, so there is nothing to compare)
    has_delay: bool

    def worse_than(self, other: Quality, slack: float = 0.1) -> list[str]:
        """Reasons this calibration is worse than ``other`` (empty: not worse). ``slack``
        is the relative margin a statistical figure may grow before it counts as worse."""
        why = []
        if self.tdcs_ok < other.tdcs_ok:
            why.append(f"calibrates {self.tdcs_ok} TDCs, the current one {other.tdcs_ok}")
        if self.inl_error_lsb > other.inl_error_lsb * (1 + slack):
            why.append(f"INL error {self.inl_error_lsb:.3f} LSB RMS against "
                       f"{other.inl_error_lsb:.3f}")
        if self.lsb_residual_ps > other.lsb_residual_ps * (1 + slack) + 0.05:  # NaN: False
            why.append(f"LSB fit residual {self.lsb_residual_ps:.3f} ps RMS against "
                       f"{other.lsb_residual_ps:.3f}")
        if other.has_delay and not self.has_delay:
            why.append("has no delay measurement, the current one has")
        return why


def quality(caldir: str | Path) -> Quality:
    calib = load_calibration(caldir)
    ok = calib.ok
    resid = np.asarray(calib.meta.get("lsb_residual_ps", []), np.float64)
    return Quality(int(ok.sum()),
                   float(np.nanmedian(calib.density.inl_error_lsb[ok])) if ok.any()
                   else float("inf"),
                   over_finite(lambda v: np.sqrt(np.mean(v ** 2)), resid) if resid.ndim == 2
                   and resid.shape[1] > 4 else float("nan"),
                   calib.has_delay)
