"""A measured instrument response, and the matched filter and maximum likelihood that use it.

A real SPAD's return is not a Gaussian: it rises in a bin or two and decays over tens of
bins (carrier diffusion), and the Gaussian estimators' centre of such a peak moves with its
width and with the background. A response measured on the same instrument (a capture at a
known distance, or a reference channel such as the ams TMF8820's internal optical path, a
zero-distance return in every capture) is the model instead: the return is that response,
shifted and scaled, on a flat background.

The response is kept bin-integrated (the fraction of a return's photons in each bin) and
shifted by a fraction of a bin through its cumulative sum (a monotone PCHIP interpolation),
so a shifted model is again bin-integrated and sums to the same total. Fits run on the
pile-up corrected counts (:meth:`~stages.ranging.histograms.Histograms.intensity` times the
cycles; with unknown cycles no correction, which the caller says).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator

from stages.models.tcspc import FWHM_PER_SIGMA
from stages.ranging.detection import _background, _detection, scan_bins, time_profile
from stages.ranging.histograms import Estimate, Histograms, coates
from stages.ranging.validation import _safe, check_histograms, check_p_fa, finish

#: the estimators that take a measured response
IRF_ESTIMATORS = ("matched", "ml")
#: the least relative error of a measured response as a model of one return, a bin (the
#: TMF8820's zones: ~3 % apart a bin near the mode, a shift interpolated within a bin
#: ~10 % on a one-bin rising edge)
RESPONSE_ERROR = 0.2
#: ... and the most (a bin where one row's tail is 3x the mean is that row's, not noise)
RESPONSE_ERROR_MAX = 3.0
#: fine shift step (bins) of the search, refined by a parabola
_STEP = 0.1
#: a measured response keeps the bins from this many times its rise (mode to half
#: maximum on the leading side) ahead of its mode, and no fewer than :data:`LEAD_BINS`:
#: a Gaussian's 3.5 sigma (a fixed 4 bins cut a 2.3-bin sigma at 1.7 of them, 2.7 % of
#: its counts, and ml's times with it wandered by up to 1.4 mm with the return's place in
#: its bin, issue 34)
RISE_SPANS = 3.0
#: ... the least (a SPAD's one-bin rise: the bins before it are background)
LEAD_BINS = 4


@dataclass(frozen=True)
class Response:
    """A measured instrument response on a uniform time axis.

    ``density`` (n,) the fraction of a return's photons in each bin (sums to 1, background
    removed); ``bin_s`` the bin width it was measured with; ``source`` what it was measured
    on (named in every output that uses it). Time zero of the response is the leading edge
    of its mode bin: a return fitted with shift ``s`` bins arrives at ``(mode + s) * bin_s``.
    """

    density: np.ndarray
    bin_s: float
    source: str
    #: per bin, the relative error of the density as a model of one return (measured on
    #: the returns it was averaged from, :func:`response_from_returns`); None: not known
    error: np.ndarray | None = None

    def __post_init__(self):
        d = np.asarray(self.density, np.float64)
        if d.ndim != 1 or d.size < 3 or not np.all(np.isfinite(d)) or np.any(d < 0) \
                or d.sum() <= 0:
            raise ValueError(f"response {self.source!r}: needs >= 3 finite, non-negative "
                             "bins with a positive sum")
        if not (np.isfinite(self.bin_s) and self.bin_s > 0):
            raise ValueError(f"response {self.source!r}: bin width must be > 0 s, found "
                             f"{self.bin_s!r}")
        object.__setattr__(self, "density", d / d.sum())
        if self.error is not None:
            e = np.asarray(self.error, np.float64)
            if e.shape != d.shape or not np.all(np.isfinite(e)) or np.any(e < 0):
                raise ValueError(f"response {self.source!r}: its error needs one finite, "
                                 "non-negative value a bin")
            object.__setattr__(self, "error", e)

    @property
    def mode(self) -> int:
        return int(np.argmax(self.density))

    @property
    def span(self) -> tuple[int, int]:
        """Bins before and after the mode that the fits use: 1 % to 90 % of the response
        (the far tail, where one channel's diffusion differs from another's, left out)."""
        cum = np.cumsum(self.density)
        lo = int(np.searchsorted(cum, 0.01))
        hi = int(np.searchsorted(cum, 0.9))
        return max(self.mode - lo, 1) + 1, max(hi - self.mode, 2) + 1

    @property
    def sigma_s(self) -> float:
        """The Gaussian of the same FWHM (for the estimators that take a Gaussian): the
        long tail left out, as it is by the Gaussian's own width."""
        return _fwhm_bins(self) * self.bin_s / FWHM_PER_SIGMA

    def models(self, shifts: np.ndarray, n_bins: int, values=None) -> np.ndarray:
        """Bin-integrated models (len(shifts), n_bins): the response with its mode bin
        moved to bin ``shift`` (``mode + s`` with s = shift - mode), each summing to the
        part of the response inside the window (``values``, one a bin of the density, is
        moved instead where given: e.g. the density times its error)."""
        cum, f = self._interpolator(values)
        e = np.arange(n_bins + 1)[None, :] - (np.asarray(shifts, np.float64)[:, None]
                                               - self.mode)
        v = np.where(e <= 0, 0.0, np.where(e >= cum.size - 1, cum[-1],
                                           f(np.clip(e, 0, cum.size - 1))))
        return np.diff(v, axis=1)


    def whole_bins(self, n_bins: int) -> np.ndarray:
        """:meth:`models` at every whole bin (n_bins, n_bins), kept on the instance."""
        cache = self.__dict__.setdefault("_whole", {})
        if n_bins not in cache:
            cache[n_bins] = self.models(np.arange(n_bins, dtype=np.float64), n_bins)
        return cache[n_bins]

    def _interpolator(self, values=None):
        """(cumulative sum, its monotone interpolator) of the density or ``values``, kept
        on the instance (a search asks for the same ones hundreds of times)."""
        cache = self.__dict__.setdefault("_interpolators", {})
        d = self.density if values is None else np.asarray(values, np.float64)
        key = None if values is None else d.tobytes()
        if key not in cache:
            cum = np.concatenate([[0.0], np.cumsum(d)])
            cache[key] = (cum, PchipInterpolator(np.arange(cum.size, dtype=np.float64), cum,
                                                 extrapolate=False))
        return cache[key]


def response_from_counts(counts, bin_s: float, source: str, cycles=None) -> Response:
    """The response of a histogram of a single return (a reference channel, or a capture
    at a known distance with nothing else in view): pile-up corrected when ``cycles`` is
    known, then as :func:`response_from_returns` treats each of its rows: the background
    (:func:`_backgrounds`) taken out, nothing kept before :func:`lead_bins` ahead of the
    mode (3 rises: a SPAD's one-bin rise keeps 4 bins, a Gaussian pulse 3.5 sigma), and
    clipped at 0.

    >>> r = response_from_counts([1, 1, 1, 1, 1, 1, 51, 31, 11, 6, 1, 1], 1e-10, "demo")
    >>> r.mode, round(float(r.density[6]), 2)
    (6, 0.53)
    """
    c = np.asarray(counts, np.float64)
    if c.ndim != 1 or c.size < 3 or not np.all(np.isfinite(c)) or np.any(c < 0):
        raise ValueError(f"response {source!r}: counts must be >= 3 finite, non-negative "
                         "values")
    if cycles is not None and np.isfinite(cycles) and cycles > c.sum():
        c = coates(c, cycles) * cycles
    d = _without_background(c[None, :], np.array([int(np.argmax(c))]))[0]
    return Response(np.clip(d, 0.0, None), float(bin_s), source)


def _backgrounds(y, k, lead: int) -> np.ndarray:
    """Each row's background: the mean of its bins more than ``lead`` before its mode
    bin ``k``, else (fewer than 4 of them) the median of its last quarter. (The median
    of a few counts a bin is below their mean, 0 at 0.5 a bin: what it left stood in the
    response as a pedestal to the window's end, 8 % of a return of 2 000 counts.)"""
    n = y.shape[1]
    out = np.empty(y.shape[0])
    for i in range(y.shape[0]):  # per row: a mean over a variable span (a few rows)
        pre = y[i, : max(k[i] - lead, 0)]
        out[i] = np.mean(pre) if pre.size >= 4 else np.median(y[i, -max(n // 4, 1):])
    return out


def lead_bins(y, k) -> int:
    """Bins ahead of the mode that a response measured on the rows ``y`` (each a return
    whose mode is in bin ``k``) keeps: :data:`RISE_SPANS` times the rise of their sum
    (each row's background taken out, the rows aligned on ``k``), no fewer than
    :data:`LEAD_BINS`."""
    y = np.atleast_2d(np.asarray(y, np.float64))
    k = np.asarray(k, np.int64)
    bg = _backgrounds(y, k, LEAD_BINS)
    j = np.arange(int(k.max()) + 1)
    at = k[:, None] - j[None, :]
    reach = at >= 0
    v = np.where(reach, np.take_along_axis(y, np.clip(at, 0, None), 1) - bg[:, None],
                 0.0).sum(0) / np.maximum(reach.sum(0), 1)
    below = np.flatnonzero(v < v[0] / 2)
    if not v[0] > 0 or not below.size:
        return LEAD_BINS
    i = below[0]  # the half maximum crossed between i - 1 and i
    rise = i - 1 + (v[i - 1] - v[0] / 2) / (v[i - 1] - v[i])
    return max(LEAD_BINS, int(np.ceil(RISE_SPANS * rise)))


def _without_background(y, k) -> np.ndarray:
    """The rows ``y`` (returns whose modes are in bins ``k``) less each one's background
    (:func:`_backgrounds`), not clipped at 0 (each row's positive fluctuations clipped
    alone add up to a pedestal: the caller clips their average), nothing kept before
    :func:`lead_bins` ahead of the mode."""
    lead = lead_bins(y, k)
    d = y - _backgrounds(y, k, lead)[:, None]
    d[np.arange(y.shape[1])[None, :] < (np.asarray(k) - lead)[:, None]] = 0.0
    return d


def _solve(models, y, wts):
    """Weighted least squares of y ~ a * model + b for every (pixel, shift): a, b."""
    # models (S, n) or (P, S, n); y, wts (P, 1, n)
    sw, sy = wts.sum(-1), (wts * y).sum(-1)
    sm, smm = (wts * models).sum(-1), (wts * models * models).sum(-1)
    smy = (wts * models * y).sum(-1)
    det = sw * smm - sm * sm
    ok = det > 0
    det = np.where(ok, det, 1.0)
    a = np.where(ok, (sw * smy - sm * sy) / det, 0.0)
    b = np.where(ok, (smm * sy - sm * smy) / det, sy / np.maximum(sw, 1e-300))
    return a, b


def _deviance(y, m, sel):
    """Poisson deviance of counts y against model m over the bins ``sel``."""
    m = np.maximum(m, 1e-9)
    yy = np.maximum(y, 0.0)
    term = m - yy + np.where(yy > 0, yy * np.log(np.where(yy > 0, yy, 1.0) / m), 0.0)
    return 2 * np.where(sel, term, 0.0).sum(-1)


def fit_response(h: Histograms, response: Response, estimator: str = "ml",
                 p_fa: float = 1e-3) -> Estimate:
    """Arrival time of each row's return with a measured ``response`` on the histograms'
    uniform bins: ``matched`` (the largest correlation of the corrected counts with the
    response over fine shifts) or ``ml`` (Poisson maximum likelihood of shift, amplitude
    and background, its sigma from the likelihood's curvature). Detection as every
    estimator's (:func:`~stages.ranging.detection._detection` at ``p_fa``).
    """
    if estimator not in IRF_ESTIMATORS:
        raise ValueError(f"a measured response is used by {IRF_ESTIMATORS}, found "
                         f"{estimator!r}")
    p_fa = check_p_fa(p_fa)
    flags = check_histograms(h)  # the estimators' own checks; a bad row flagged, not fitted
    safe = _safe(h, flags)
    if safe.counts.shape[0] == 0 or safe.counts.shape[1] < 3:
        raise ValueError(f"histograms need >= 1 row of >= 3 bins, found shape "
                         f"{safe.counts.shape}")
    return finish(_fit(safe, response, estimator, p_fa), safe, response.sigma_s, flags)


def _fit(h: Histograms, response: Response, estimator: str, p_fa: float) -> Estimate:
    bin_s = float(h.bin_s)
    if not np.allclose(h.widths[np.isfinite(h.widths)], bin_s, rtol=1e-6):
        raise ValueError("a measured response needs uniform bins (an instrument's own time "
                         "axis)")
    if abs(response.bin_s / bin_s - 1) > 0.01:
        raise ValueError(f"response {response.source!r} was measured with "
                         f"{response.bin_s * 1e12:.4g} ps bins, these histograms have "
                         f"{bin_s * 1e12:.4g} ps")
    n_pix, n = h.counts.shape
    rows = np.arange(n_pix)
    y = h.intensity() * h.cycles[:, None]               # pile-up corrected counts
    y = np.where(h.valid, y, 0.0)
    lo, hi = response.span
    # coarse: the whole-bin shift of the largest correlation (background-free response)
    whole = response.whole_bins(n)                                        # (n, n)
    base = np.median(np.where(h.valid, y, np.nan), axis=1)
    base = np.where(np.isfinite(base), base, 0.0)
    corr = (y - base[:, None]) @ whole.T                                   # (P, n)
    corr = np.where(h.valid, corr, -np.inf)
    k0 = np.argmax(corr, axis=1)
    # fine: shifts within 1.2 bins of it, each pixel its own grid
    off = np.arange(-1.2, 1.2 + 1e-9, _STEP)
    shifts = k0[:, None] + off[None, :]                                    # (P, S)
    # only the bins the fit weighs (the span around k0, within a window of whole blocks
    # of 8 bins, as multi_irf._fit: numpy's pairwise sums then add the same numbers in
    # the same order as over every bin, whose other weights are 0); over the whole
    # window (~1,000 bins, ~97 % of them weighed 0) the fit took 4-8 s on 400 rows
    width = -(-(lo + hi + 8) // 8) * 8
    start = np.zeros(n_pix, np.int64)
    if width < n:
        start = np.clip(np.minimum((k0 - lo) // 8 * 8, n - width), 0, None)
    else:
        width = n
    kk = start[:, None] + np.arange(width)[None, :]                        # (P, W)
    models = window_models(response, shifts.ravel(), np.repeat(start, off.size),
                           width).reshape(n_pix, off.size, width)
    valid = np.take_along_axis(h.valid, kk, 1)
    sel = (valid & (kk >= k0[:, None] - lo) & (kk <= k0[:, None] + hi))[:, None, :]
    yy = np.take_along_axis(y, kk, 1)[:, None, :]
    if estimator == "matched":
        zm = models - np.where(sel, models, 0).sum(-1, keepdims=True) / np.maximum(
            sel.sum(-1, keepdims=True), 1)
        score = -(np.where(sel, zm * yy, 0).sum(-1) / np.sqrt(np.maximum(
            np.where(sel, zm * zm, 0).sum(-1), 1e-300)))
    wts = np.where(sel, 1.0 / np.maximum(yy, 1.0), 0.0)
    a, b = _solve(models, yy, wts)
    for _ in range(2):  # reweighted to the model: Pearson, close to Poisson ML
        m = a[..., None] * models + b[..., None]
        wts = np.where(sel, 1.0 / np.maximum(m, 1.0), 0.0)
        a, b = _solve(models, yy, wts)
    m = np.maximum(a, 0)[..., None] * models + np.maximum(b, 0)[..., None]
    dev = _deviance(yy, m, sel)
    if estimator == "ml":
        score = dev
    j = np.clip(np.argmin(score, axis=1), 1, off.size - 2)
    s_m, s_0, s_p = score[rows, j - 1], score[rows, j], score[rows, j + 1]
    curv = s_m - 2 * s_0 + s_p
    frac = np.where(curv > 0, 0.5 * (s_m - s_p) / np.where(curv > 0, curv, 1.0), 0.0)
    frac = np.clip(frac, -1.0, 1.0)
    shift = shifts[rows, j] + frac * _STEP
    amp, bg = np.maximum(a[rows, j], 0.0), np.maximum(b[rows, j], 0.0)
    # sigma: the deviance's curvature (deviance = -2 log L + const) in bins^2
    dcurv = (dev[rows, j - 1] - 2 * dev[rows, j] + dev[rows, j + 1]) / _STEP ** 2
    sigma_bins = np.where(dcurv > 0, np.sqrt(2.0 / np.where(dcurv > 0, dcurv, 1.0)), np.inf)
    signal = amp * response.models(shift, n).sum(1)
    if estimator == "matched":  # the matched filter's own spread: the response's / sqrt(N)
        sigma_bins = response.sigma_s / bin_s / np.sqrt(np.maximum(signal, 1.0))
    t_s = h.edges_s[rows, 0] + shift * bin_s
    peak = np.clip(np.rint(shift).astype(np.int64), 0, n - 1)
    # detection against the estimators' background (a mean over the gate away from the
    # return, without the bins that stand out), not the fit's local one: that is clipped
    # at 0 and, on a handful of counts in the response's span, was 0 in most rows at 0.1
    # counts a bin (ml called 21-434 of 2 000 background-only rows at p_fa 1e-3-0.05,
    # issue 34.4); the window of the scan statistic as the Gaussian estimators' at the
    # response's FWHM
    kk = np.arange(n)[None, :]
    away = h.valid & ((kk < peak[:, None] - 2 * lo) | (kk > peak[:, None] + 2 * hi))
    rate = _background(h.lam, h.widths, away, h.at_risk)
    bg = rate * h.cycles * bin_s
    # a background not flat in time over a batch on one axis: the detection's background
    # in bin j is the rate times width_j times the profile's s_j (docs/ranging.md)
    profile = time_profile(h)
    ws = h.widths if profile is None else h.widths * profile[None, :]
    rate_d = rate if profile is None else _background(h.lam, ws, away, h.at_risk)
    detected = _detection(h.counts, h.valid, h.at_risk, ws, peak, rate_d, p_fa,
                          scan=scan_bins(response.sigma_s, bin_s))
    sane = np.isfinite(t_s) & np.isfinite(sigma_bins) & (amp > 0)
    fwhm = _fwhm_bins(response) * bin_s
    return Estimate(t_s, np.where(sane, sigma_bins * bin_s, np.inf), np.full(n_pix, fwhm),
                    signal, bg, detected & sane, estimator + "+irf")


def window_models(response: Response, shifts, start, width: int) -> np.ndarray:
    """:meth:`Response.models` of the bins ``start`` to ``start + width - 1`` only (each
    shift its own ``start``): the same numbers."""
    cum, f = response._interpolator()
    e = (np.asarray(start)[:, None] + np.arange(width + 1)[None, :]) - (
        np.asarray(shifts, np.float64)[:, None] - response.mode)
    v = np.where(e <= 0, 0.0, np.where(e >= cum.size - 1, cum[-1],
                                       f(np.clip(e, 0, cum.size - 1))))
    return np.diff(v, axis=1)


def _fwhm_bins(response: Response) -> float:
    """Full width at half maximum in bins, the crossings interpolated linearly."""
    d, k = response.density, response.mode
    half = d[k] / 2
    below = np.flatnonzero(d[:k] < half)
    left = float(k)
    if below.size:
        i = below[-1]
        left = i + (half - d[i]) / (d[i + 1] - d[i])
    below = np.flatnonzero(d[k:] < half)
    right = float(d.size - 1)
    if below.size:
        i = k + below[0]
        right = i - 1 + (d[i - 1] - half) / (d[i - 1] - d[i])
    return max(right - left, 1.0)


def response_from_returns(h: Histograms, t_s, source: str) -> Response:
    """The response of the returns themselves: every row with a finite time ``t_s`` (one
    return each: captures of a single target at known distances, or each pixel's strongest
    return), pile-up corrected, its background (:func:`_backgrounds`) taken out, shifted
    by a fraction of a bin (its cumulative sum interpolated) so that the times coincide,
    and averaged bin by bin over the rows that reach that bin (a row late in the window
    has its tail cut by the window's end), each row normalised over the bins that every
    row reaches, and the average clipped at 0.
    Nothing is kept before :func:`lead_bins` ahead of the mode. The rows' responses must
    share a shape (the TMF8820's zones agree within ~3 % a bin); a reference channel's
    (another optical path) need not be theirs."""
    bin_s = float(h.bin_s)
    t = np.asarray(t_s, np.float64)
    use = np.flatnonzero(np.isfinite(t))
    if not use.size:
        raise ValueError(f"response {source!r}: no return to measure it on")
    n = h.counts.shape[1]
    y = np.where(h.valid, h.intensity() * h.cycles[:, None], 0.0)[use]
    pos = (t[use] - h.edges_s[use, 0]) / bin_s                # the times in bins
    k = np.clip(np.floor(pos).astype(np.int64), 0, n - 1)
    d = _without_background(y, k)
    lead = pos - pos.min()                                     # >= 0: shift each row early
    cum = np.concatenate([np.zeros((use.size, 1)), np.cumsum(d, axis=1)], axis=1)
    x = np.arange(n + 1)[None, :] + lead[:, None]
    aligned = np.diff(np.array([np.interp(xi, np.arange(n + 1), ci, right=np.nan)
                                for xi, ci in zip(x, cum, strict=True)]), axis=1)
    reach = np.isfinite(aligned)
    common = reach.all(axis=0)
    norm = np.where(common, np.nan_to_num(aligned), 0.0).sum(axis=1)
    good = norm > 0
    if not good.any():
        raise ValueError(f"response {source!r}: no return above its background")
    a = np.nan_to_num(aligned[good]) / norm[good, None]
    density = np.clip(a.sum(axis=0) / np.maximum(reach[good].sum(axis=0), 1), 0.0, None)
    # each bin's error: the largest relative departure of a row from the mean, over the
    # bin and its neighbours (a shift of a bin), no lower than RESPONSE_ERROR
    dev = np.where(reach[good], np.abs(a - density), 0.0).max(axis=0)
    rel = np.where(density > 0, dev / np.where(density > 0, density, 1.0), 0.0)
    rel = np.maximum.reduce([rel, np.roll(rel, 1), np.roll(rel, -1)])
    return Response(density, bin_s, source,
                    error=np.maximum(np.minimum(rel, RESPONSE_ERROR_MAX), RESPONSE_ERROR))
