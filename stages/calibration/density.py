"""Calibration, the density test (sections 3.2, 5.1): DNL, INL and LSB of every TDC.

Uniform light makes every code's share of hits proportional to its width, once pile-up is
undone: the first photon is likelier early in the window, which is at high codes (reversed
timing). Going through the codes in arrival order (high to low), a code's hits over the
cycles still "at risk" (no START at a higher code) is ``1 - exp(-r w)``: so
``r w = -log(1 - h / R)`` exactly, at any light level (Coates' correction). The top codes
hold the reset peak (a START at the window's beginning, tau = T); their widths come from the
measured codes of the same VCO phase (the DNL pattern repeats every 8 codes).

Statistics: with H hits over K codes, the INL has an RMS statistical error of about
``K sqrt(1/6) / sqrt(H)`` LSB (the cumulative count is binomial): ~0.32 LSB for 250 000 hits
(1e6 cycles at 25 % STARTs) over 395 codes, 0.1 LSB at ~1e7 cycles. :func:`cycles_needed`
turns a requested INL precision into cycles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.constants import N_CODES
from stages.calibration.reset_peak import EDGE_MARGIN, RESET_HALF, at_risk_by_code, fit_reset_peak


@dataclass(frozen=True)
class DensityResult:
    """Per-TDC results of a density test. Widths, DNL and INL are (n_tdc, 512)."""

    lsb_s: np.ndarray        #: window over code span
    x_t: np.ndarray          #: where tau = T falls on the code axis
    width_lsb: np.ndarray    #: code widths (NaN above the window)
    dnl_lsb: np.ndarray
    inl_lsb: np.ndarray      #: at each code's lower boundary
    hits: np.ndarray         #: hits per TDC used
    detections_per_cycle: np.ndarray  #: STARTs per cycle, the light level of eq. 5.1
    ok: np.ndarray           #: False for a dead or dark TDC (flagged, excluded)
    inl_error_lsb: np.ndarray  #: expected statistical error of the mid-range INL
    #: per TDC, why it is flagged ("" where ok or where no reason was recorded)
    reasons: tuple = ()
    #: variance (code^2) of ``x_t``: its reset peak fit's own (:func:`x_t_variance`);
    #: None where not known (a table read back, a result built by hand)
    x_t_var: np.ndarray | None = None

    def __post_init__(self):
        n = int(np.asarray(self.lsb_s).size)
        reasons = tuple(self.reasons) or ("",) * n
        if len(reasons) != n:
            raise ValueError(f"density test: {len(reasons)} reasons for {n} TDCs")
        object.__setattr__(self, "reasons", tuple(str(r) for r in reasons))

    @property
    def n_tdc(self) -> int:
        return int(self.lsb_s.size)

    def flagged(self, bad, why) -> DensityResult:
        """This result with the TDCs ``bad`` flagged (``ok`` False, results NaN) for
        ``why`` (one reason, or one per TDC); a TDC already flagged keeps its reason."""
        bad = np.asarray(bad, bool) & np.asarray(self.ok, bool)
        if not bad.any():
            return self
        why = [why] * self.n_tdc if isinstance(why, str) else list(why)
        reasons = tuple(w if b else r for b, w, r in zip(bad, why, self.reasons,
                                                        strict=True))
        nan = {f: np.where(bad if np.ndim(getattr(self, f)) == 1 else bad[:, None],
                           np.nan, getattr(self, f))
               for f in ("lsb_s", "x_t", "width_lsb", "dnl_lsb", "inl_lsb", "inl_error_lsb",
                         "x_t_var") if getattr(self, f) is not None}
        import dataclasses

        return dataclasses.replace(self, ok=np.asarray(self.ok, bool) & ~bad,
                                   reasons=reasons, **nan)


#: RMS over the codes of sqrt(F (1 - F)) for F uniform on [0, 1]: sqrt(1/6).
INL_RMS_FACTOR = float(np.sqrt(1 / 6))


def cycles_needed(inl_rms_lsb: float, n_codes: float = 395.0,
                  starts_per_cycle: float = 0.25) -> int:
    """Cycles a density test needs for an INL with ``inl_rms_lsb`` statistical RMS error.

    The cumulative count below code k is binomial, so the INL's error there is
    ``K sqrt(F (1 - F) / H)``; its RMS over the codes is ``K sqrt(1/6) / sqrt(H)``.

    >>> cycles_needed(0.1)  # ~1e7 cycles at 25 % STARTs per cycle
    10401667
    """
    hits = (n_codes * INL_RMS_FACTOR / inl_rms_lsb) ** 2
    return int(np.ceil(hits / starts_per_cycle))


def density_test(hits: np.ndarray, cycles: np.ndarray, window_s: float,
                 min_hits: int = 1000, exclude: np.ndarray | None = None,
                 fill: tuple[np.ndarray, np.ndarray] | None = None,
                 artifacts: np.ndarray | None = None, combine: bool = False) -> DensityResult:
    """DNL, INL and LSB of every TDC from the D1st histograms of a uniform-light capture.

    Parameters
    ----------
    hits : (n_tdc, 512) counts of hit words (artifact removed).
    cycles : (n_tdc,) cycles per TDC.
    window_s : the window length T.
    min_hits : below this a TDC is flagged as dead or dark (``ok = False``), and its
        results are NaN; other TDCs are unaffected. So is a TDC whose histogram lacks a
        phase (:func:`phase_depleted`: not uniform light).
    exclude : (n_tdc, 512) bool, optional
        Codes whose counts are not uniform light (a range capture's signal peaks): their
        hits still leave the at-risk count, their widths come from the phase means.
    fill : ((n_tdc, 512), (n_tdc, 512)), optional
        Widths of the codes this test cannot measure (under its reset peak) as other tests
        measured them, and their variances (any unit common to a row; NaN where unknown),
        from :func:`fill_from`. Each such code takes the inverse-variance mean of that and
        the phase mean (whose error is the scatter of this test's own widths about it): the
        random DNL of those 3-5 codes otherwise tilts the whole table (their summed width
        sets where T falls).
    artifacts : (n_tdc, 512), optional
        Artifact words by code (``HistogramAccumulator(count_artifacts=True)``). An artifact
        is a START: its cycle is not at risk at later codes. Without them the at-risk
        counts after each artifact code are too high by its rate (the simulated chip's
        ~1e-4 a cycle at three codes), every width there too small by as much, and the
        INL bows by ~0.015 LSB (~3 ps) mid-window.
    combine : bool
        With ``fill``, every code this test measured also takes the inverse-variance mean
        of its own width and the fill's: the INL then has the statistics of all the tests
        (the DNL does not change with light, only the LSB), not only this one's.
    """
    hits = np.asarray(hits, np.float64)
    cycles = np.asarray(cycles, np.float64)
    n_tdc = hits.shape[0]
    out = {k: np.full(n_tdc, np.nan) for k in ("lsb", "x_t", "err", "x_var")}
    widths = np.full((n_tdc, N_CODES), np.nan)
    inl = np.full((n_tdc, N_CODES), np.nan)
    total = hits.sum(axis=1)
    ok = total >= min_hits
    reasons = np.where(ok, "", f"under {min_hits} hits (dead or dark)").astype(object)
    for t in np.flatnonzero(ok):  # a loop over TDCs, once per calibration
        res = _one_tdc(hits[t], cycles[t], window_s,
                       None if exclude is None else exclude[t],
                       None if fill is None else (fill[0][t], fill[1][t]),
                       None if artifacts is None else np.asarray(artifacts[t], np.float64),
                       combine)
        if res is None or isinstance(res, str):
            ok[t] = False
            reasons[t] = res or "no reset peak, or under 32 codes below it"
            continue
        out["lsb"][t], out["x_t"][t], widths[t], inl[t], out["err"][t], out["x_var"][t] = res
    dnl = widths - 1.0
    return DensityResult(out["lsb"], out["x_t"], widths, dnl, inl, total, total / cycles, ok,
                         out["err"], tuple(reasons.tolist()), out["x_var"])


#: Codes the reset peak (x_T) may sit from where a density test's light ends.
RESET_PLAUSIBLE = 8


def light_stop(row: np.ndarray) -> int | None:
    """One past the last code of one TDC's histogram holding a tenth of the median
    populated code's count: where uniform light ends (tau = T), which a stray count above
    does not move; None for an empty histogram."""
    pos = row[row > 0]
    if not pos.size:
        return None
    return int(np.flatnonzero(row >= 0.1 * np.median(pos))[-1]) + 1


def implausible_reset_peak(hits: np.ndarray, res: DensityResult) -> np.ndarray:
    """Per TDC, why the density test's reset peak cannot be where the window ends ("" where
    it can). Uniform light fills every code up to tau = T and nothing comes after it, so
    x_T sits where the light ends (the last code holding a tenth of the median code's
    count, a stray count above does not move it); a peak found ``RESET_PLAUSIBLE`` codes
    or more away from there is something else (an artifact's code counted as hits: x_T
    139 for ~364, LSB 573 ps for ~220, issue 15), and its LSB would be wrong."""
    h = np.asarray(hits, np.float64)
    why = np.full(h.shape[0], "", dtype=object)
    for t in np.flatnonzero(np.asarray(res.ok, bool)):
        end = light_stop(h[t])
        if end is None:
            continue
        if abs(res.x_t[t] - end) >= RESET_PLAUSIBLE:
            why[t] = (f"reset peak at code {res.x_t[t]:.0f}, but the light ends at code "
                      f"{end}: not where the window ends (LSB {res.lsb_s[t] * 1e12:.0f} ps "
                      "implausible)")
    return why


#: A phase (P1st, code mod 8) of a uniform-light histogram holding less than this share
#: of the phases' mean count per code: words lost, not light (see :func:`phase_depleted`).
PHASE_MIN_SHARE = 0.25


def phase_depleted(hits: np.ndarray, codes=None) -> np.ndarray:
    """(n_tdc,) True where a uniform-light histogram lacks a phase: some P1st (code mod 8)
    holds under ``PHASE_MIN_SHARE`` of the phases' mean count per code over
    ``codes`` (default: 8 to 8 codes below the reset peak). Uniform light fills every
    phase in proportion to its width (the chips' per-phase DNL is well within a factor
    of 2); an empty phase means words were dropped before the histogram, e.g. by artifact
    bounds (n_min, n_max) a bright test's own second stage got wrong (chip zoo seed 119:
    its brightest test, 0.84 detections a cycle, kept only P1st 4 and 5 on six of eight
    TDCs). Such a histogram gives neither widths (combined into every other test's INL
    with the tiny variances of its many counts) nor an LSB, nor its light level."""
    h = np.atleast_2d(np.asarray(hits, np.float64))
    out = np.zeros(h.shape[0], bool)
    for t, row in enumerate(h):
        if codes is None:
            top = int(np.argmax(np.where(np.arange(N_CODES) > 16, row, -1)))
            k = np.arange(8, max(top - EDGE_MARGIN - 4, 8))
        else:
            k = np.asarray(codes)
        if k.size < 16:
            continue
        ph = np.array([row[k[k % 8 == p]].mean() if np.any(k % 8 == p) else np.nan
                       for p in range(8)])
        mean = np.nanmean(ph)
        out[t] = bool(mean > 0 and np.nanmin(ph) < PHASE_MIN_SHARE * mean)
    return out


def _one_tdc(h: np.ndarray, n_cycles: float, window_s: float, exclude=None, fill=None,
             artifacts=None, combine=False):
    # the reset peak: the largest count in the upper part of the code range; with returns
    # in the histogram (``exclude``) the largest count near where the light ends, since a
    # return can count more than the reset peak (an LSB of ~590 ps for ~220 from a return
    # at code ~136 taken for tau = T: issue 26.8)
    k = np.arange(N_CODES)
    zone = k > 16
    end = light_stop(h) if exclude is not None else None
    if end is not None:
        zone &= np.abs(k - end) < RESET_PLAUSIBLE
    top = int(np.argmax(np.where(zone, h, -1)))
    # The low edge is usable: for uniform light, code 0 (which also collects every START the
    # jitter pushes below tau = 0) holds density * B_1 * (1 + ~0.004) at sigma = 0.5 LSB
    # (integral of Phi), and code 1 loses ~1 %: measured directly they beat any fill.
    lo, hi = 0, top - EDGE_MARGIN           # the reset peak's codes are excluded
    if hi - lo < 32:
        return None
    # at risk before each code, in arrival order (high codes first)
    at_risk = at_risk_by_code(h[None], [n_cycles], artifacts)[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        rw = -np.log1p(-h / at_risk)        # r * width, Coates
    interior = np.arange(lo, hi + 1)
    if exclude is not None:
        interior = interior[~exclude[interior]]
        if interior.size < 32 or any(np.sum(interior % 8 == p) == 0 for p in range(8)):
            return None
    if phase_depleted(h[None], interior)[0]:
        return None  # not uniform light: words of some phases were lost
    if np.any(~np.isfinite(rw[interior])) or np.any(h[interior] == 0):
        # missing codes: a zero-count code has an unknown (tiny) width; keep it at 0
        rw = np.where(np.isfinite(rw), rw, 0.0)
    # dead (missing) codes: no count between lit codes, also under the reset peak; and
    # beyond it, where a fill's test measured them (no width, to its 1 / R)
    dead = dead_codes(h, top)
    if fill is not None and np.isfinite(fill[0]).any():
        with np.errstate(invalid="ignore"):
            dead |= ((h == 0) & np.isfinite(fill[0]) & np.isfinite(fill[1])
                     & (fill[0] <= 0.1 * np.nanmedian(fill[0])))
    near = dead | np.roll(dead, 1) | np.roll(dead, -1)
    # per-phase mean widths fill the edge codes (the DNL pattern repeats every 8 codes),
    # over live codes whose neighbours are live (a dead code's time is in a neighbour)
    typical = interior[~near[interior]]
    if any(np.sum(typical % 8 == p) == 0 for p in range(8)):
        typical = interior
    phase_mean = np.array([rw[typical[typical % 8 == p]].mean() for p in range(8)])
    scale = rw[interior].mean()             # r * LSB_interior
    w = rw / scale
    edge = np.ones(N_CODES, bool)
    edge[interior] = False
    w[edge] = phase_mean[np.arange(N_CODES)[edge] % 8] / scale
    measured = ~edge
    if fill is not None:
        w = _refill(w, edge, interior, phase_mean / scale,
                    _expected_var(h, at_risk, ~edge) / scale ** 2, *fill, combine=combine,
                    loose=near & ~dead)
        measured |= edge & np.isfinite(fill[0]) & np.isfinite(fill[1]) & (fill[1] > 0)
    pm = phase_mean[np.arange(N_CODES) % 8] / scale

    def peak(w):  # x_T: the reset peak fitted over these boundaries, above the uniform
        # part (the interior's density, at risk there) that ends at T
        bound = np.concatenate([[0.0], np.cumsum(w)])   # B_k in interior-LSB units
        P, _, _, ll = fit_reset_peak(h[None], at_risk[None], bound[None], np.array([top]),
                                     np.array([scale]), loglik=True)
        return bound, float(P[0]), float(ll[0])  # P in interior-LSB units

    w, why = _dead_widths(w, dead, measured, pm, peak)
    if why:
        return why
    if OWN_TOP:
        w = _own_top_widths(h, at_risk, w, top, hi, scale, dead)
    bound, tau_t, _ = peak(w)
    if not np.isfinite(tau_t):
        return None
    k = int(np.searchsorted(bound, tau_t, side="right") - 1)
    if not 0 <= k < w.size:  # the fitted window's end beyond the codes: no x_T here (the
        return None          # range stage's LSB tracking on the test pattern raised)
    x_t = k + (tau_t - bound[k]) / w[k]
    x_var = x_t_variance(h, at_risk, w, top, scale, x_t,
                         _expected_var(h, at_risk, np.arange(N_CODES) <= hi) / scale ** 2)
    lsb = window_s / x_t
    # rescale to the window's LSB: B_k (s) = bound * T / tau_t
    b_lsb = bound * x_t / tau_t
    inl = b_lsb[:N_CODES] - np.arange(N_CODES)
    width = np.diff(b_lsb)
    beyond = np.arange(N_CODES) > x_t
    if fill is not None:
        # beyond the window the table continues over the codes other (dimmer) tests
        # measured: the time axis at a dimmer light reads its x_T there
        known = np.isfinite(fill[0]) & np.isfinite(fill[1]) & (fill[1] > 0)
        gap = np.flatnonzero(beyond & ~known)
        beyond = np.arange(N_CODES) >= (gap[0] if gap.size else N_CODES)
    width[beyond] = np.nan
    inl[beyond] = np.nan
    err = x_t * INL_RMS_FACTOR / np.sqrt(max(h[interior].sum(), 1.0))
    return lsb, x_t, width, inl, err, x_var


#: Codes below the reset peak's highest count (and :data:`RESET_HALF` above it) whose
#: widths :func:`x_t_variance` carries into x_T: the fit's codes and two more.
X_T_CODES = (-RESET_HALF - 2, RESET_HALF)


def x_t_variance(h, at_risk, w, top, scale, x_t, own_var, eps: float = 0.02) -> float:
    """Variance (code^2) of one TDC's x_T (its reset peak fitted over its widths ``w``,
    interior-LSB units, by :func:`fit_reset_peak`): the fit's own, the inverse of its
    Fisher information (the peak's counts), and what the widths of the codes under and
    around the peak put there, ``sum_j g_j^2 v_j`` with ``g_j = dx_T / dw_j`` (the fit
    repeated with ``w_j + eps``) and ``v_j`` the test's own counting where it measured the
    code (``own_var``, codes clear of the peak by :data:`OWN_CLEAR_LSB`), else the random
    DNL about the phase pattern those codes took (:func:`.uncertainty.pattern_var`).
    NaN where the fit fails."""
    from stages.calibration.uncertainty import pattern_var

    lo, hi = X_T_CODES
    codes = np.arange(max(top + lo, 0), min(top + hi, w.size - 1) + 1)
    bound = np.concatenate([[0.0], np.cumsum(w)])
    rows = np.vstack([bound[None]] + [bound + eps * (np.arange(bound.size) > j)
                                      for j in codes])
    n = rows.shape[0]
    P, _, _, pv = fit_reset_peak(np.broadcast_to(h, (n, h.size)),
                                 np.broadcast_to(at_risk, (n, h.size)), rows,
                                 np.full(n, top), np.full(n, scale), p_var=True)
    k = np.clip((rows <= P[:, None]).sum(axis=1) - 1, 0, w.size - 1)
    r = np.arange(n)
    with np.errstate(all="ignore"):
        x = k + (P - rows[r, k]) / (rows[r, k + 1] - rows[r, k])
    if not np.all(np.isfinite(x)):
        return float("nan")
    g = (x[1:] - x[0]) / eps
    measured = np.arange(w.size) < np.floor(x_t - OWN_CLEAR_LSB)
    v = np.where(measured & np.isfinite(own_var), own_var, np.nan)
    v = np.where(np.isfinite(v), v, pattern_var(w[None], v[None])[0])
    fisher = pv[0] / max(float(w[int(np.clip(np.floor(x_t), 0, w.size - 1))]), 1e-3) ** 2
    return float(fisher + np.sum(g * g * v[codes]))


#: Codes whose upper boundary lies this many LSB or more below tau = T are measured by the
#: test's own counts (the reset peak's Gaussian tail and the light's blurred end taken off,
#: as :func:`fit_reset_peak` models them); :func:`width_variance` gives them a variance.
OWN_CLEAR_LSB = 2.5
#: Whether the last codes below the reset peak are measured so (issue 33); before, they
#: took the other tests' widths or the phase mean: a dimmer capture's window ends there.
OWN_TOP = True


def _own_top_widths(h, at_risk, w, top, hi, scale, dead, rounds: int = 2):
    """``w`` (interior-LSB units) with the codes above ``hi`` (the interior's last) that
    lie clear of the reset peak measured from this test's own counts: each code's width
    solves ``h_j = R_j (1 - exp(-u share_j)) + A (Phi(z_j+1) - Phi(z_j))`` (its light up to
    where it ends at T, blurred, and the reset peak's tail), going up from ``hi`` (every
    boundary is the sum of the widths below), with (P, s, A) the reset peak fitted over
    the boundaries; fitted again after, ``rounds`` times."""
    from scipy.special import ndtr

    def phi(z):
        return np.exp(-0.5 * z * z) / np.sqrt(2 * np.pi)

    def share(lo, up, P, s):  # the part of [lo, up) before T, blurred by s
        ya, yb = (P - lo) / s, (P - up) / s
        return s * ((ya * ndtr(ya) + phi(ya)) - (yb * ndtr(yb) + phi(yb)))

    w = w.copy()
    grid = np.linspace(0.0, 3.0, 601)  # candidate widths, 0.005 apart, refined below
    for _ in range(rounds):
        bound = np.concatenate([[0.0], np.cumsum(w)])
        P, s, A = (float(v[0]) for v in fit_reset_peak(
            h[None], at_risk[None], bound[None], np.array([top]), np.array([scale])))
        if not (np.isfinite(P) and np.isfinite(s)):
            return w  # no peak to take off
        lo = bound[hi + 1]
        for j in range(hi + 1, w.size):
            if dead[j] or h[j] <= 0 or at_risk[j] <= h[j]:
                break

            def resid(c, j=j, lo=lo, P=P, s=s, A=A):
                up = lo + c
                return (at_risk[j] * -np.expm1(-scale * share(lo, up, P, s))
                        + A * (ndtr((up - P) / s) - ndtr((lo - P) / s)) - h[j])

            r = resid(grid)
            k = int(np.argmax(r >= 0)) if np.any(r >= 0) else -1
            if k <= 0:
                break
            a, b = grid[k - 1], grid[k]
            for _ in range(30):  # bisection: the model rises with the width
                m = 0.5 * (a + b)
                a, b = (m, b) if resid(m) < 0 else (a, m)
            c = 0.5 * (a + b)
            if lo + c > P - OWN_CLEAR_LSB:
                break
            w[j] = c
            lo += c
    return w


#: A run of zero-count codes between two codes of at least this many counts is dead
#: (zero width): a live code there (width >= ~0.45 LSB) expects a third of the smaller
#: neighbour's count or more (uniform light, or a log-concave reset peak), ~10 at 30.
DEAD_LIT = 30
#: Log-likelihood (nats) by which the reset peak must prefer one placement of a dead
#: code's time (one neighbour or the other) when the two x_T differ by ``DEAD_XT_CODES``
#: or more; below it the TDC is flagged.
DEAD_LL, DEAD_XT_CODES = 3.0, 0.05


def dead_codes(h: np.ndarray, top: int) -> np.ndarray:
    """(512,) bool: the codes of ``h`` (one TDC's histogram) up to the reset peak's reach
    (``top + RESET_HALF``) with no count between two codes of ``DEAD_LIT`` or more. A
    dead (missing) code of the first stage has zero width, its time is in a neighbour;
    under the reset peak its count is the only sign of it."""
    h = np.asarray(h)
    out = np.zeros(h.size, bool)
    end = min(int(top) + RESET_HALF + 1, h.size - 1)
    k = 1
    while k < end:
        if h[k] != 0:
            k += 1
            continue
        j = k
        while j < h.size and h[j] == 0:
            j += 1
        if j < h.size and h[k - 1] >= DEAD_LIT and h[j] >= DEAD_LIT:
            out[k:j] = True
        k = j
    return out


def beside_dead(w: np.ndarray) -> np.ndarray:
    """A TDC's dead codes (a finite width of zero or less: no count between lit codes,
    their time in a neighbour) and the codes either side of one, along the last axis: the
    widths a phase pattern does not predict."""
    w = np.asarray(w, np.float64)
    dead = np.isfinite(w) & (w <= 0)
    out = dead.copy()
    out[..., 1:] |= dead[..., :-1]
    out[..., :-1] |= dead[..., 1:]
    return out


def _dead_widths(w, dead, measured, pm, peak):
    """``w`` (interior-LSB units) with every dead code at zero width and its time given to
    the neighbour that holds it. A measured neighbour (``measured``: by this test's light
    or a fill) holds it where it is wider than its phase mean by half the dead code's
    phase mean; an unmeasured one (under the reset peak, given its phase mean) takes
    ``pm`` of the dead code when the other neighbour is measured and does not hold it.
    Where neither neighbour is measured the reset peak decides (``peak(w)``: its
    likelihood over each placement); where it cannot (within ``DEAD_LL`` nats, x_T
    ``DEAD_XT_CODES`` apart) the reason is returned with ``w``, else "".

    A dead code given its phase mean instead (as before) put one code too many under the
    reset peak: x_T 1.06 codes high, LSB 0.78 ps low on chip zoo seed 5 (n_sat 0.4, dead
    code 327, x_T 328.2), the delay 252 ps off."""
    import itertools

    w = w.copy()
    ambiguous = []
    for d in np.flatnonzero(dead):
        w[d] = 0.0
        nb = [j for j in (d - 1, d + 1) if 0 <= j < w.size and not dead[j]]
        free = [j for j in nb if not measured[j]]
        if not free:
            continue  # the time is where it was measured
        held = [j for j in nb if measured[j] and w[j] - pm[j] > 0.5 * pm[d]]
        if held:
            continue
        if len(free) == 1:
            w[free[0]] += pm[d]
        else:
            ambiguous.append((d, free))
    if not ambiguous:
        return w, ""
    tries = []
    for pick in itertools.product(*(f for _, f in ambiguous)):
        c = w.copy()
        for (d, _), j in zip(ambiguous, pick, strict=True):
            c[j] += pm[d]
        bound, tau_t, ll = peak(c)
        tries.append((ll if np.isfinite(ll) and np.isfinite(tau_t) else -np.inf, tau_t, c,
                      bound))
    tries.sort(key=lambda x: -x[0])
    best = tries[0]
    x_t = [_x_of(b, t, c) for _, t, c, b in tries]
    close = [i for i in range(1, len(tries)) if best[0] - tries[i][0] < DEAD_LL
             and abs(x_t[i] - x_t[0]) >= DEAD_XT_CODES]
    if close:
        codes = ", ".join(str(d) for d, _ in ambiguous)
        return best[2], (f"dead code {codes} under the reset peak: which neighbour holds its "
                         f"time the data cannot tell (x_T {x_t[0]:.2f} or "
                         f"{x_t[close[0]]:.2f})")
    return best[2], ""


def _x_of(bound, tau_t, w):
    """The code axis' x at ``tau_t`` on ``bound`` (widths ``w``)."""
    if not np.isfinite(tau_t):
        return np.nan
    k = int(np.clip(np.searchsorted(bound, tau_t, side="right") - 1, 0, w.size - 1))
    return k + (tau_t - bound[k]) / w[k] if w[k] > 0 else float(k)


def width_variance(hits: np.ndarray, cycles: np.ndarray, density: DensityResult,
                   artifacts: np.ndarray | None = None) -> np.ndarray:
    """(n_tdc, 512) variance of each measured code width (LSB^2), NaN for the codes the
    test did not measure (under its reset peak, beyond the window, empty, dead TDCs).

    The variance of Coates' ``r w`` at the code's expected count (:func:`_expected_var`)
    scaled to the width. A dead code
    (:func:`dead_codes`; its width 0) is measured too, to ``1 / R`` of ``r w`` (R cycles
    at risk, no count): a test that fills from this one then knows it has no width (given
    its phase mean instead, the codes under the reset peak and the table beyond the window
    would hold one code too many).
    """
    h = np.asarray(hits, np.float64)
    r = at_risk_by_code(h, cycles, artifacts)
    k = np.arange(N_CODES)[None, :]
    last = (np.floor(density.x_t - OWN_CLEAR_LSB) if OWN_TOP
            else np.floor(density.x_t) - EDGE_MARGIN - 1)
    inside = (k < last[:, None]) & density.ok[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        per_rw = density.width_lsb / -np.log1p(-h / r)   # LSB per unit of r w
        var = _expected_var(h, r, inside) * per_rw ** 2
    measured = inside & (h > 0)
    var = np.where(measured & np.isfinite(var) & (var > 0), var, np.nan)
    for t in np.flatnonzero(np.asarray(density.ok, bool)):
        top = int(np.argmax(np.where(np.arange(N_CODES) > 16, h[t], -1)))
        dead = dead_codes(h[t], top) & inside[t]
        if dead.any():
            with np.errstate(invalid="ignore"):
                unit = np.nanmedian(np.where(measured[t], per_rw[t], np.nan))
            var[t, dead] = (unit / np.maximum(r[t, dead], 1.0)) ** 2
    return var


def fill_from(tests: list[tuple[DensityResult, np.ndarray]], target: DensityResult):
    """Code widths for ``density_test(fill=...)``: the inverse-variance mean over ``tests``
    (each a result and its :func:`width_variance`), every test first brought to
    ``target``'s units by the ratio of their mean widths over the codes both measured
    (the LSB changes with light; the DNL does not)."""
    num = np.zeros_like(target.width_lsb)
    den = np.zeros_like(target.width_lsb)
    k = np.arange(N_CODES)[None, :]
    inside = k < np.floor(target.x_t)[:, None] - EDGE_MARGIN - 1
    for res, var in tests:
        both = inside & np.isfinite(var) & np.isfinite(target.width_lsb)
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = (np.where(both, target.width_lsb, 0).sum(1)
                     / np.where(both, res.width_lsb, 0).sum(1))
        good = np.isfinite(var) & (both.sum(1) >= 32)[:, None] & np.isfinite(ratio)[:, None]
        v = np.where(good, var * ratio[:, None] ** 2, np.inf)
        num += np.where(good, res.width_lsb * ratio[:, None] / v, 0.0)
        den += np.where(good, 1 / v, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / den, np.nan), np.where(den > 0, 1 / den, np.nan)


def _coates_var(h, r):
    """The variance of Coates' ``r w = -log(1 - h / R)`` with h binomial given R (delta
    method): h / (R (R - h)); inf where every cycle at risk fired."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return h / (r * (r - h))


#: Codes each side (of the same phase, code mod 8: 8 of them, +-32 codes) over which
#: :func:`_expected_var` takes the mean count a code is expected to have.
EXPECTED_PHASE_CODES = 4


def _expected_var(h, r, measured=None):
    """:func:`_coates_var` at the count a code is *expected* to have (its Coates ``r w``
    averaged over the ``EXPECTED_PHASE_CODES`` codes of its phase each side, itself
    included), not the count it got (issue 33.3): a variance from its own count is
    smaller where the count came out low, so an inverse-variance mean of the tests leans
    toward the low ones (the widths where a dim test of ~15 counts a code meets a bright
    one came out 0.13 of their sigma low on average) and the variance it states is
    short; the expected count has neither. Codes without a count (or without the
    neighbours to average) keep their own. ``h``, ``r``: (..., 512); ``measured``: the
    codes to average over (the uniform light's, not the reset peak's; default all)."""
    h = np.asarray(h, np.float64)
    r = np.asarray(r, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        rw = -np.log1p(-h / r)
    ok = np.isfinite(rw) & (h > 0)
    if measured is not None:
        ok &= np.asarray(measured, bool)
    v = np.where(ok, rw, 0.0)
    n = ok.astype(np.float64)
    m = EXPECTED_PHASE_CODES
    mean = np.full(h.shape, np.nan)
    for p in range(8):  # each phase's codes, a running mean over 2m + 1 of them
        cs = np.cumsum(np.pad(v[..., p::8], [(0, 0)] * (h.ndim - 1) + [(m + 1, m)]), axis=-1)
        cn = np.cumsum(np.pad(n[..., p::8], [(0, 0)] * (h.ndim - 1) + [(m + 1, m)]), axis=-1)
        tot = cs[..., 2 * m + 1:] - cs[..., :-2 * m - 1]
        cnt = cn[..., 2 * m + 1:] - cn[..., :-2 * m - 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            mean[..., p::8] = np.where(cnt >= m, tot / cnt, np.nan)
    h_exp = r * -np.expm1(-mean)
    return np.where(ok & np.isfinite(h_exp) & (h_exp > 0), _coates_var(h_exp, r),
                    _coates_var(h, r))


#: What the codes a test cannot measure (filled from the other tests) are pulled toward,
#: by inverse variance: "window", the whole window's phase mean (before issue 33: a bias
#: where the chip bows, ~58 % of each code's departure from the pattern lost); "local",
#: the phase mean of the ``LOCAL_CODES`` codes below them (follows the bow; the random DNL
#: is still shrunk by its own variance against the fill's); "" none (no bias, noisier).
#: Noise-free, the time axis mid-window at 0.05 erred by 11 ps RMS (window), 26 (local),
#: 8 (none) on real-chip zoo seeds 1-4; our simulator's 512 targets: 0.259, 0.257, 0.264 cm
#: (``benchmarks/calibration_bias.py``, ``benchmarks/range_accuracy.py``).
PHASE_PULL = ""
LOCAL_CODES = 64


def _refill(w, edge, interior, phase_mean, stat_var, f_w, f_var, combine=False,
            loose=None):
    """The edge codes' widths (``w``, interior-LSB units, where ``phase_mean`` (8,) already
    stands) as the inverse-variance mean of that and ``f_w`` (another test's, any unit:
    brought to this one's by the codes both measured); ``stat_var``: the variance of each
    measured width of ``w``. With ``combine``, the measured codes too (their own width
    against ``f_w``, each by its variance). ``loose``: codes the phase mean does not
    predict (a dead code's neighbours: one of them holds its time), which take ``f_w``
    alone where it is known."""
    common = interior[np.isfinite(f_w[interior])]
    if common.size < 32:
        return w
    ratio = w[common].mean() / f_w[common].mean()
    f, fv = f_w * ratio, f_var * ratio ** 2
    near = interior[-LOCAL_CODES:] if PHASE_PULL == "local" else interior
    if PHASE_PULL == "local" and any(np.sum(near % 8 == p) == 0 for p in range(8)):
        near = interior
    if PHASE_PULL == "local":  # the pattern of the codes next to the edge: it follows the bow
        phase_mean = np.array([w[near[near % 8 == p]].mean() for p in range(8)])
    pm = phase_mean[np.arange(N_CODES) % 8]
    # the phase mean's error as a fill: the scatter of the measured widths about it, less
    # what their own statistics explain (the random DNL: what the pattern cannot know)
    stat = stat_var[near]
    spread = (np.mean((w[near] - pm[near]) ** 2)
              - (np.mean(stat[np.isfinite(stat)]) if np.isfinite(stat).any() else 0.0))
    v_pm = max(spread, 1e-8)
    use = edge & np.isfinite(f) & np.isfinite(fv) & (fv > 0)
    out = w.copy()
    if PHASE_PULL:
        out[use] = (pm[use] / v_pm + f[use] / fv[use]) / (1 / v_pm + 1 / fv[use])
    else:
        out[use] = f[use]
    if loose is not None:
        out[use & loose] = f[use & loose]
    if combine:
        sv = np.full(w.size, np.nan)
        sv[interior] = stat_var[interior]
        both = (~edge & np.isfinite(f) & np.isfinite(fv) & (fv > 0) & np.isfinite(sv)
                & (sv > 0))
        out[both] = (w[both] / sv[both] + f[both] / fv[both]) / (1 / sv[both] + 1 / fv[both])
    return out
