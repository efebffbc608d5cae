"""More than one surface a pixel with a measured instrument response: the found returns
subtracted, tail and all, before the next is searched.

A real SPAD's return decays over tens of bins (carrier diffusion; the ams TMF8820's over
~20 bins of 91 ps, a TCSPC fluorescence decay over nanoseconds). The Gaussian masks of
:mod:`stages.ranging.multi` leave that tail in the histogram, and the next search finds it
as a surface. Here each found return is modelled by the whole measured response
(:class:`~stages.ranging.irf.Response`, every bin of its density, not only its fitting
span), shifted to the return's fitted time and scaled by its fitted signal, in the pile-up
corrected domain (:meth:`~stages.ranging.histograms.Histograms.intensity` times the
cycles). The next return is fitted to the counts with the found returns' model as a fixed
part (the residual, not a mask: a second surface inside the first's tail can still be
found), and is tested against background plus that model, taken back to the counts of
the cycles still at risk as every detection here is.

Model error: a response measured on other captures is not each return's exact shape (the
TMF8820's zones differ by ~3 % a bin near the mode and some far tails by 2x, and a shift
interpolated within a bin leaves ~10 % on a one-bin rising edge). Counts of 10^5 a bin
have a Poisson spread of 0.3 %, so a few per cent of misfit would be a surface. The
model's part of every bin therefore carries the response's measured relative error
(``Response.error``, :func:`~stages.ranging.irf.response_from_returns`: the largest
departure of one averaged return from the mean, at least 20 %; :data:`MODEL_ERROR` where
the response has none): in the search's weights (the variance is the counts' plus
(error x model)^2, both times the pile-up correction's gain) and in the detection, which
tests the candidate's bin against background plus the found returns' model raised by
that error. A weaker surface is found where it stands out of the brighter one's response
by more than that error (measured in ``benchmarks/multi_return.py``). Not tested: a
candidate closer than the response's FWHM to a found return (its misfit), or where fewer
than :data:`MIN_AT_RISK` of the cycles are still at risk. The background is never taken
below the mean of the :data:`LOCAL_BINS` bins before the candidate's rise (a real
background is not flat).

False alarms, as in :mod:`stages.ranging.multi`: return k + 1 is searched only where
return k was detected, each test at ``p_fa`` over the valid bins; a background-only pixel
needs its first test to fire (<= p_fa), a pixel with real returns can be wrong only in the
test after its last real one (<= p_fa where the model error covers the misfit).

Times: the first return is the caller's single-return estimate (its estimator, its shape,
its calibration), unchanged where no further return is found. Where one is, the pixel's
returns are refitted, each with the others subtracted (after every return found), and
each is timed by the caller's estimator on the histogram with the others taken out
(:func:`deflated`), so its distance uses that estimator's calibration; else (no such
estimator given, or it lands more than a FWHM away) the first's time plus its offset in
the response's fits.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from stages.ranging.detection import _background, poisson_tail, tested_bin
from stages.ranging.histograms import Estimate, Histograms
from stages.ranging.irf import Response, _fwhm_bins
from stages.ranging.irf import window_models as _window_models

#: relative error of a found return's modelled counts in each bin (see the docstring)
MODEL_ERROR = 0.2
#: the fewest cycles still at risk (a fraction of the cycles) where a further return is
#: tested: beyond, the corrected counts hang on the pulse count more than on the photons
#: (the TMF8820 within 8 cm, its effective pulse count fitted: 3-12 % at risk 4-7 cm behind
#: the target, where 20 % of the model was not enough)
MIN_AT_RISK = 0.5
#: bins before a candidate's rise whose mean background it is tested against, at least
LOCAL_BINS = 8
#: fine shift grid of the fits (bins), refined by a parabola
_STEP = 0.1
_OFF = np.arange(-1.2, 1.2 + 1e-9, _STEP)


@dataclass(frozen=True)
class PerGroup:
    """A single-return estimator of its own for each group of rows (a batch of several
    measurements, each timed with its own reference channel's response): row ``i`` by
    ``singles[group[i]]``, each called on its group's rows only (as alone), so a batch
    gives each row what its measurement alone would. A function of :class:`Histograms` of
    its rows; :meth:`take` the estimator of some of them."""

    group: np.ndarray
    singles: Sequence[Callable[[Histograms], Estimate]]

    def take(self, rows) -> PerGroup:
        """The estimator of the rows ``rows`` (in that order)."""
        return PerGroup(np.asarray(self.group)[rows], self.singles)

    def __call__(self, h: Histograms) -> Estimate:
        parts = []
        for g in np.unique(self.group):
            idx = np.flatnonzero(self.group == g)
            parts.append((idx, self.singles[g](Histograms(
                h.counts[idx], h.edges_s[idx], h.cycles[idx], h.valid[idx]))))
        return merge_rows(parts, len(self.group))


def merge_rows(parts: list[tuple[np.ndarray, Estimate]], n: int) -> Estimate:
    """One estimate of ``n`` rows from estimates of the rows ``idx`` of each part."""
    first = parts[0][1]
    cols = {}
    for name in Estimate.__dataclass_fields__:
        vals = [getattr(e, name) for _, e in parts]
        if not any(isinstance(v, np.ndarray) for v in vals):
            cols[name] = vals[0]
            continue
        if name == "flag":
            vals = [np.full(idx.size, "", object) if v is None else v
                    for (idx, _), v in zip(parts, vals, strict=True)]
        col = np.empty(n, np.result_type(*[np.asarray(v).dtype for v in vals]))
        for (idx, _), v in zip(parts, vals, strict=True):
            col[idx] = v
        cols[name] = col
    return Estimate(**cols) if len(parts) > 1 else first


def _corrected(h: Histograms) -> np.ndarray:
    """Pile-up corrected counts of every bin (0 on invalid bins)."""
    return np.where(h.valid, h.intensity() * h.cycles[:, None], 0.0)


def _variance(y, known, kerr, gain, fit=None):
    """Each bin's variance: the corrected counts' (Poisson, at least 1, times ``gain``, the
    cycles over the cycles at risk: the correction's amplification) plus the found
    returns' model error ``kerr`` (counts a bin), amplified alike."""
    base = np.maximum(y if fit is None else fit + known, 1.0) * gain
    return base + (gain * kerr) ** 2


def _coarse(y, valid, gain, known, kerr, response: Response) -> np.ndarray:
    """The whole-bin position of the most significant excess over ``known``: the
    correlation of the residual with the response over the square root of its variance
    (a misfit under the found returns' peaks does not outweigh a surface beside them)."""
    n = y.shape[1]
    whole = response.whole_bins(n)                                        # (n, n)
    r = np.where(valid, y - known, 0.0)
    base = np.median(np.where(valid, r, np.nan), axis=1)
    base = np.where(np.isfinite(base), base, 0.0)
    var = np.where(valid, _variance(y, known, kerr, gain), 0.0)
    score = ((r - base[:, None]) @ whole.T) / np.sqrt(np.maximum(var @ (whole ** 2).T,
                                                                 1e-300))
    return np.argmax(np.where(valid, score, -np.inf), axis=1)


def _fit(y, valid, gain, known, kerr, response: Response, centre):
    """Shift (bins: the response's mode bin), amplitude, background per bin and sigma
    (bins) of one return per row near the whole-bin ``centre``, fitted to ``y`` with the
    other returns' model ``known`` fixed: weighted least squares of amplitude and
    background at each shift of a 0.1-bin grid (weights from the model, twice
    reweighted), the chi-square's minimum by a parabola, sigma from its curvature."""
    n_pix, n = y.shape
    rows = np.arange(n_pix)
    lo, hi = response.span
    shifts = centre[:, None] + _OFF[None, :]                              # (P, S)
    # only the bins the fit weighs (the span around centre, within a window of whole
    # blocks of 8 bins: numpy's pairwise sums then add the same numbers in the same order
    # as over every bin, whose other weights are 0)
    width = -(-(lo + hi + 8) // 8) * 8
    start = np.zeros(n_pix, np.int64)
    if width < n:
        start = np.clip(np.minimum((centre - lo) // 8 * 8, n - width), 0, None)
        y, valid, gain, known, kerr = (np.take_along_axis(
            np.broadcast_to(a, (n_pix, n)), start[:, None] + np.arange(width)[None, :], 1)
            for a in (y, valid, gain, known, kerr))
    else:
        width = n
    models = _window_models(response, shifts.ravel(), np.repeat(start, _OFF.size),
                            width).reshape(n_pix, _OFF.size, width)
    kk = start[:, None] + np.arange(width)[None, :]
    sel = (valid & (kk >= centre[:, None] - lo) & (kk <= centre[:, None] + hi))[:, None, :]
    r, yy, kn = (y - known)[:, None, :], y[:, None, :], known[:, None, :]
    gg, ke = gain[:, None, :], kerr[:, None, :]
    wts = np.where(sel, 1.0 / _variance(yy, kn, ke, gg), 0.0)
    for _ in range(3):
        a, b = _solve(models, r, wts)
        fit = np.maximum(a, 0)[..., None] * models + np.maximum(b, 0)[..., None]
        wts = np.where(sel, 1.0 / _variance(yy, kn, ke, gg, fit), 0.0)
    chi2 = (wts * (r - fit) ** 2).sum(-1)                                  # (P, S)
    j = np.clip(np.argmin(chi2, axis=1), 1, _OFF.size - 2)
    s_m, s_0, s_p = chi2[rows, j - 1], chi2[rows, j], chi2[rows, j + 1]
    curv = s_m - 2 * s_0 + s_p
    frac = np.clip(np.where(curv > 0, 0.5 * (s_m - s_p) / np.where(curv > 0, curv, 1.0),
                            0.0), -1.0, 1.0)
    shift = shifts[rows, j] + frac * _STEP
    sigma = np.where(curv > 0, np.sqrt(2.0 / np.where(curv > 0, curv, 1.0)) * _STEP, np.inf)
    return shift, np.maximum(a[rows, j], 0.0), np.maximum(b[rows, j], 0.0), sigma


def _solve(models, y, wts):
    from stages.ranging.irf import _solve as solve

    return solve(models, y, wts)


def _model(response: Response, shift, amp, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Each row's return, the whole response at ``shift`` times ``amp`` (P, n), and its
    error a bin (the response's own where it was measured, else :data:`MODEL_ERROR`)."""
    err = response.error if response.error is not None else np.full(
        response.density.size, MODEL_ERROR)
    ok = np.isfinite(shift)[:, None]
    s, a = np.nan_to_num(shift), np.nan_to_num(amp)[:, None]
    return (np.where(ok, a * response.models(s, n), 0.0),
            np.where(ok, a * response.models(s, n, response.density * err), 0.0))


def _models(response: Response, shifts, amps, n: int, rows=slice(None), skip=None):
    """The sum of :func:`_model` over the returns ``shifts``, ``amps`` (but ``skip``)."""
    known = kerr = 0.0
    for i, (s, a) in enumerate(zip(shifts, amps, strict=True)):
        if i != skip:
            m, e = _model(response, s[rows], a[rows], n)
            known, kerr = known + m, kerr + e
    return known, kerr


def _detected(h: Histograms, y, shift, amp, known, kerr, p_fa, lead: int) -> np.ndarray:
    """The candidate's bin (:func:`tested_bin` of the bin holding ``shift``) against the
    background plus the found returns' model ``known`` raised by its error ``kerr``
    (times the pile-up correction's gain there), taken to the
    raw counts of the cycles at risk; Poisson tail at ``p_fa`` over the valid bins. The
    background is the estimators' (:func:`~stages.ranging.detection._background`: a mean
    without the bins that stand out) of the corrected counts ``y`` less ``known``, no lower
    than one count over the valid bins' exposure (as :func:`_detection`'s: a median called
    0 at 0.3 counts a bin, and every count a return), and no lower than the mean over the
    :data:`LOCAL_BINS` valid bins before the candidate's rise (``lead`` bins before its
    mode): a real sensor's background is not flat (the TMF8820's rises ~20 % across its
    window, and a flat one called that slope a return)."""
    rows = np.arange(shift.size)
    n = h.counts.shape[1]
    cyc = np.maximum(np.asarray(h.cycles, np.float64), 1.0)
    w = h.widths
    rate = _background(np.clip(y - known, 0.0, None) / cyc[:, None], w, h.valid, h.at_risk)
    exposure = np.where(h.valid, np.maximum(h.at_risk, 0.0) * w, 0.0).sum(axis=1)
    rate = np.maximum(rate, 1.0 / np.maximum(exposure, 1e-300))
    k = np.clip(np.floor(np.nan_to_num(shift)), 0, n - 1).astype(np.int64)
    q = tested_bin(h.counts, h.valid, k)
    kk = np.arange(n)[None, :]
    near = h.valid & (kk < (k - lead)[:, None]) & (kk >= (k - lead - LOCAL_BINS)[:, None])
    local = np.where(near, np.clip(y - known, 0.0, None) / cyc[:, None], 0.0).sum(axis=1) \
        / np.maximum(np.where(near, w, 0.0).sum(axis=1), 1e-300)
    rate = np.where(near.sum(axis=1) >= LOCAL_BINS // 2, np.maximum(rate, local), rate)
    gain = h.cycles / np.maximum(h.at_risk[rows, q], 1.0)
    lam = rate * w[rows, q] + (known[rows, q] + gain * kerr[rows, q]) / cyc
    b = np.maximum(h.at_risk[rows, q], 0.0) * -np.expm1(-lam)
    n_bins = np.maximum(np.asarray(h.valid).sum(axis=1), 1)
    return (poisson_tail(h.counts[rows, q], b) <= p_fa / n_bins) & (amp > 0) & \
        np.isfinite(shift) & (gain <= 1 / MIN_AT_RISK)


def deflated(h: Histograms, y: np.ndarray, others: np.ndarray) -> Histograms:
    """``h`` with the returns ``others`` (corrected counts a bin) taken out: its corrected
    counts ``y`` less them (not below 0), piled up again with its cycles (each bin's
    expected first-photon count, rounded), on the same bins."""
    lam = np.clip(y - others, 0.0, None) / np.maximum(h.cycles, 1.0)[:, None]
    out = np.empty_like(lam)
    risk = np.asarray(h.cycles, np.float64).copy()
    for j in range(lam.shape[1]):  # bin by bin: the cycles still at risk (a few hundred)
        out[:, j] = np.rint(risk * -np.expm1(-lam[:, j]))
        risk = np.maximum(risk - out[:, j], 0.0)
    return Histograms(np.where(h.valid, out, h.counts), h.edges_s, h.cycles, h.valid)


def further_returns(h: Histograms, response: Response, first: Estimate, p_fa: float,
                    max_returns: int, single=None) -> list[dict]:
    """Up to ``max_returns`` returns of each row of ``h`` (its uniform bins, the
    response's): ``first`` the rows' single-return estimate, searched further where it is
    detected (see the module docstring). Where a row has several, each return's time and
    sigma are ``single``'s (the caller's single-return estimator, a function of
    :class:`Histograms`) on the row with the other returns taken out (:func:`deflated`),
    else the first's plus its offset in the response's fits; its sigma the larger of
    ``single``'s and the response fit's (whose variance holds the other returns' model
    error). Returns one dict of per-row
    columns a return (``t_s``, ``sigma_s``, ``fwhm_s``, ``signal_counts``,
    ``background_per_bin``, ``detected``), the first's own columns where no further return
    was found (a row whose first is not detected is not searched)."""
    n_pix = h.counts.shape[0]
    live = np.flatnonzero(np.asarray(first.detected, bool))
    firsts = {name: np.asarray(getattr(first, name), np.float64) for name in
              ("t_s", "sigma_s", "fwhm_s", "signal_counts", "background_per_bin")}
    out = [{**{k: v.copy() for k, v in firsts.items()},
            "detected": np.asarray(first.detected, bool).copy()}]
    if max_returns == 1 or not live.size:
        return out
    sub = Histograms(h.counts[live], h.edges_s[live], h.cycles[live], h.valid[live])
    found = _search(sub, response, {k: v[live] for k, v in firsts.items()}, p_fa,
                    max_returns, single.take(live) if isinstance(single, PerGroup) else single)
    for i, cols in enumerate(found):
        if i == len(out):
            out.append({k: np.full(n_pix, np.nan) for k in firsts}
                       | {"detected": np.zeros(n_pix, bool)})
        for k, v in cols.items():
            out[i][k][live] = v
    return out


def _search(h: Histograms, response: Response, first: dict, p_fa: float, max_returns: int,
            single) -> list[dict]:
    """:func:`further_returns` on rows whose first return is detected (``first``: its
    columns)."""
    n_pix, n = h.counts.shape
    bin_s = float(h.bin_s)
    y = _corrected(h)
    valid = np.asarray(h.valid, bool)
    gain = np.maximum(h.cycles[:, None] / np.maximum(h.at_risk, 1.0), 1.0)
    live = np.ones(n_pix, bool)
    zero = np.zeros_like(y)
    # the first return's response fit where the caller's estimate put it (two returns of
    # one strength: the caller's and the coarse search's pick may differ)
    at = (first["t_s"] - h.edges_s[:, 0]) / bin_s
    centre = np.where(np.isfinite(at), np.rint(np.nan_to_num(at)),
                      _coarse(y, valid, gain, zero, zero, response)).astype(np.int64)
    s0, a0, _, sig0 = _fit(y, valid, gain, zero, zero, response, np.clip(centre, 0, n - 1))
    shifts, amps, sigmas = [s0.copy()], [a0], [sig0]
    dets = [live.copy()]
    apart = _fwhm_bins(response)

    def refit(rows):
        """Each found return of ``rows`` refitted with the others subtracted, twice."""
        for _ in range(2):
            for i in range(len(shifts)):
                ok = dets[i][rows]
                if not ok.any():
                    continue
                known, kerr = _models(response, shifts, amps, n, rows, skip=i)
                centre = np.rint(np.nan_to_num(shifts[i][rows], nan=0.0)).astype(np.int64)
                s, a, _, sig = _fit(y[rows], valid[rows], gain[rows], known, kerr, response,
                                    centre)
                shifts[i][rows] = np.where(ok, s, shifts[i][rows])
                amps[i][rows] = np.where(ok, a, amps[i][rows])
                sigmas[i][rows] = np.where(ok, sig, sigmas[i][rows])

    while len(shifts) < max_returns and live.any():
        # only the rows whose last return was found (each row's arithmetic its own)
        at = np.flatnonzero(live)
        hl = Histograms(h.counts[at], h.edges_s[at], h.cycles[at], h.valid[at])
        known, kerr = _models(response, shifts, amps, n, at)
        yl, vl, gl = y[at], valid[at], gain[at]
        centre = _coarse(yl, vl, gl, known, kerr, response)
        sl, al, _, sgl = _fit(yl, vl, gl, known, kerr, response, centre)
        dl = _detected(hl, yl, sl, al, known, kerr, p_fa, response.span[0]) & \
            np.isfinite(sgl)
        with np.errstate(invalid="ignore"):  # closer than a FWHM: a misfit of the other
            dl &= np.all([~(np.abs(sl - f[at]) < apart) for f in shifts], axis=0)
        det = np.zeros(n_pix, bool)
        det[at] = dl
        s, a, sig = (np.full(n_pix, np.nan) for _ in range(3))
        s[at], a[at], sig[at] = sl, al, sgl
        shifts.append(np.where(det, s, np.nan))
        amps.append(np.where(det, a, 0.0))
        sigmas.append(sig)
        dets.append(det)
        live = det
        if det.any():
            refit(np.flatnonzero(det))
    k = len(shifts)
    several = np.zeros(n_pix, bool) if k == 1 else dets[1]
    fwhm = _fwhm_bins(response) * bin_s
    out = []
    for i in range(k):
        signal = amps[i] * response.models(np.nan_to_num(shifts[i]), n).sum(1)
        t = first["t_s"] + (shifts[i] - s0) * bin_s
        cols = {"t_s": t, "sigma_s": sigmas[i] * bin_s, "fwhm_s": np.full(n_pix, fwhm),
                "signal_counts": signal, "background_per_bin":
                first["background_per_bin"].copy(), "detected": dets[i]}
        if i == 0:  # the first as the caller's estimator gave it, unless it has company
            for name in ("t_s", "sigma_s", "fwhm_s", "signal_counts"):
                cols[name] = np.where(several, cols[name], first[name])
        out.append(cols)
    rows = np.flatnonzero(several)
    if single is not None and rows.size:
        _retime(h, y, response, shifts, amps, rows, single, out, fwhm)
    for i, cols in enumerate(out):  # no detection without a finite time and sigma
        bad = ~(np.isfinite(cols["t_s"]) & np.isfinite(cols["sigma_s"])
                & (cols["sigma_s"] > 0))
        if i:
            cols["detected"] &= ~bad
        else:  # the first as the caller gave it
            for name in ("t_s", "sigma_s", "fwhm_s", "signal_counts"):
                cols[name] = np.where(bad, first[name], cols[name])
    return out


def _retime(h, y, response, shifts, amps, rows, single, out, fwhm) -> None:
    """Each return of ``rows`` timed by ``single`` with the other returns taken out (in
    place in ``out``), where that lands within a FWHM of the response fit's time."""
    n, k, bin_s = h.counts.shape[1], len(out), float(h.bin_s)
    sub = Histograms(h.counts[rows], h.edges_s[rows], h.cycles[rows], h.valid[rows])
    if isinstance(single, PerGroup):
        single = single.take(rows)
    for i in range(k):
        e = single(deflated(sub, y[rows], _models(response, shifts, amps, n, rows, i)[0]))
        t, sig = np.asarray(e.t_s, np.float64), np.asarray(e.sigma_s, np.float64)
        ok = out[i]["detected"][rows] & np.isfinite(t) & np.isfinite(sig) & \
            (np.abs(t - out[i]["t_s"][rows]) <= max(fwhm, bin_s))
        out[i]["t_s"][rows] = np.where(ok, t, out[i]["t_s"][rows])
        # its sigma no smaller than the response fit's, whose variance holds the other
        # returns' model error (the single estimator's counts only the photons)
        out[i]["sigma_s"][rows] = np.where(ok, np.fmax(sig, out[i]["sigma_s"][rows]),
                                           out[i]["sigma_s"][rows])
