"""Calibration: density test (DNL, INL, LSB, Nmin/Nmax/Nth/PDM), LSB against light, delay.

Density test (sections 3.2, 5.1). Uniform light makes every code's share of hits
proportional to its width, once pile-up is undone: the first photon is likelier early in
the window, which is at high codes (reversed timing). Going through the codes in arrival
order (high to low), a code's hits over the cycles still "at risk" (no START at a higher
code) is ``1 - exp(-r w)``: so ``r w = -log(1 - h / R)`` exactly, at any light level
(Coates' correction). The top codes hold the reset peak (a START at the window's beginning,
tau = T); their widths come from the measured codes of the same VCO phase (the DNL pattern
repeats every 8 codes).

The LSB is the window over the code span (the issue's definition, and the one the
simulator's truth uses): ``LSB = T / x_T`` where ``x_T`` is where tau = T falls on the code
axis: the reset peak (a delta at T blurred by the TDC's jitter) fitted over the measured
code boundaries (:func:`fit_reset_peak`). INL_k = B_k / LSB - k at each code boundary B_k.

Statistics: with H hits over K codes, the INL has an RMS statistical error of about
``K sqrt(1/6) / sqrt(H)`` LSB (the cumulative count is binomial): ~0.32 LSB for 250 000 hits
(1e6 cycles at 25 % STARTs) over 395 codes, 0.1 LSB at ~1e7 cycles. :func:`cycles_needed`
turns a requested INL precision into cycles.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from schemas.constants import N_CODES, N_CODES_2ND
from schemas.errors import CalibrationError
from stages.artifact import ArtifactBounds, estimate_bounds

#: Codes excluded next to the reset peak and at the window's end (jitter is ~0.5 LSB rms).
EDGE_MARGIN = 4
#: Half-width (codes) of the region the reset peak is fitted in (+-8 jitter sigmas).
RESET_HALF = 4


def at_risk_by_code(hits, cycles, artifacts=None) -> np.ndarray:
    """(n, 512) cycles still at risk before each code, in arrival order (high codes first,
    reversed timing): the cycles less the STARTs at higher codes (hits, and artifacts
    where counted)."""
    h = np.asarray(hits, np.float64)
    if artifacts is not None:
        h = h + np.asarray(artifacts, np.float64).reshape(h.shape)
    before = np.concatenate([np.cumsum(h[:, ::-1], axis=1)[:, ::-1][:, 1:],
                             np.zeros((h.shape[0], 1))], axis=1)
    return np.asarray(cycles, np.float64).reshape(-1, 1) - before


# ----------------------------------------------------------------- the reset peak (tau = T)

def fit_reset_peak(h, at_risk, bounds, top, u, sigma0: float = 0.5, iterations: int = 15,
                   loglik: bool = False):
    """Where tau = T falls, in the units of ``bounds``: a binned Poisson fit of the reset
    peak over the codes' actual boundaries, for every row at once.

    The reset peak is a START at tau = T blurred by the TDC's jitter: code k holds
    ``A (Phi(z_k+1) - Phi(z_k))`` of it, with ``z = (b - P) / s``; below it the uniform
    light, which ends at T (blurred the same way): ``r_k (1 - exp(-u share_k))``, where
    ``share_k`` is the part of the code before T. A centroid of code centres is biased by
    the DNL where T happens to fall (up to +-0.1 code, tested): 14 ps of delay at
    mid-window. Fisher scoring on (P, s, A), steps limited to half a code.

    Parameters
    ----------
    h, at_risk : (n, 512) hits and cycles still at risk per code.
    bounds : (n, 513) code boundaries (any unit, increasing).
    top : (n,) int, the code of the reset peak's highest count.
    u : (n,) the uniform light in detections per unit of ``bounds`` per cycle at risk.

    Returns ``(P, s, A)``, each (n,); P is NaN where the peak holds no excess. With
    ``loglik``, also the Poisson log-likelihood of the fitted codes (up to a constant):
    two sets of ``bounds`` for the same counts are compared by it.
    """
    from scipy.special import ndtr  # (where used: reading a calibration needs no scipy)

    h = np.asarray(h, np.float64)
    n = h.shape[0]
    rows = np.arange(n)[:, None]
    idx = np.clip(np.asarray(top)[:, None] + np.arange(-RESET_HALF, RESET_HALF + 1), 0,
                  h.shape[1] - 1)
    hk, rk = h[rows, idx], np.maximum(np.asarray(at_risk, np.float64)[rows, idx], 0.0)
    lo, hi = bounds[rows, idx], bounds[rows, idx + 1]
    u = np.asarray(u, np.float64)[:, None]
    with np.errstate(all="ignore"):  # missing codes (zero width) around the peak
        w = np.where(hi - lo > 0, hi - lo, np.nan)
        width = np.nanmedian(np.where(np.isfinite(w).any(axis=1, keepdims=True), w, 1.0),
                             axis=1)
    # start: the centroid of the counts above the uniform level
    ex = np.clip(hk - rk * -np.expm1(-u * (hi - lo)), 0, None)
    tot = ex.sum(1)
    P = np.where(tot > 0, (ex * 0.5 * (lo + hi)).sum(1) / np.maximum(tot, 1e-300),
                 0.5 * (lo[:, RESET_HALF] + hi[:, RESET_HALF]))
    s = sigma0 * width
    A = np.maximum(tot, 1.0)

    def phi(z):
        return np.exp(-0.5 * z * z) / np.sqrt(2 * np.pi)

    def model(P, s, A):
        sc = s[:, None]
        za, zb = (lo - P[:, None]) / sc, (hi - P[:, None]) / sc
        g = ndtr(zb) - ndtr(za)
        pa, pb = phi(za), phi(zb)
        ya, yb = -za, -zb  # (P - b) / s
        share = sc * ((ya * ndtr(ya) + pa) - (yb * ndtr(yb) + pb))
        e = np.exp(-u * share)
        un = rk * (1 - e)
        return sc, za, zb, g, pa, pb, ya, yb, e, np.maximum(A[:, None] * g + un, 1e-12)

    for _ in range(iterations):
        sc, za, zb, g, pa, pb, ya, yb, e, mu = model(P, s, A)
        jac = np.stack([A[:, None] * -(pb - pa) / sc + rk * e * u * (ndtr(ya) - ndtr(yb)),
                        A[:, None] * -(zb * pb - za * pa) / sc + rk * e * u * (pa - pb),
                        g], axis=-1)
        score = np.einsum("nk,nki->ni", hk / mu - 1, jac)
        info = np.einsum("nk,nki,nkj->nij", 1 / mu, jac, jac)
        info += np.eye(3)[None] * 1e-12 * np.trace(info, axis1=1, axis2=2)[:, None, None]
        try:
            step = np.linalg.solve(info, score[..., None])[..., 0]
        except np.linalg.LinAlgError:
            break
        step = np.where(np.isfinite(step), step, 0.0)
        P = P + np.clip(step[:, 0], -0.5 * width, 0.5 * width)
        s = np.clip(s + np.clip(step[:, 1], -0.5 * s, 0.5 * s), 0.05 * width, 3 * width)
        A = np.maximum(A + step[:, 2], 1.0)
    P = np.where(tot > 0, P, np.nan)
    if loglik:
        mu = model(np.nan_to_num(P), s, A)[-1]
        return P, s, A, (hk * np.log(mu) - mu).sum(1)
    return P, s, A


# ---------------------------------------------------------------- second stage (eq. 3.4)

class SecondStageAccumulator:
    """Joint counts of (TDC, P1st, D2nd) over hit candidates, for Nmin/Nmax/Nth/PDM."""

    def __init__(self, n_tdc: int):
        self.n_tdc = n_tdc
        self.counts = np.zeros((n_tdc, 8, N_CODES_2ND), np.int64)

    def update(self, words: np.ndarray, first_word: int = 0) -> None:
        from stages.codec import classify_words, decode_fields

        f = decode_fields(words)
        cls = classify_words(words, self.n_tdc, first_word, fields=f)
        ok = cls == 0  # hit candidates: no artifact test yet (bounds unknown)
        pos = (np.arange(words.size) + first_word) % self.n_tdc
        key = (pos[ok] * 8 + f.p1st[ok]) * N_CODES_2ND + f.d2nd[ok]
        self.counts += np.bincount(key, minlength=self.counts.size).reshape(self.counts.shape)


@dataclass(frozen=True)
class SecondStage:
    n_min: np.ndarray
    n_max: np.ndarray
    n_th: np.ndarray
    pdm: np.ndarray
    #: per TDC, why its bounds cannot be trusted ("" where they can; () where none is
    #: recorded): :attr:`stages.artifact.ArtifactBounds.reasons` of the estimate
    reasons: tuple = ()

    @property
    def uncertain(self) -> np.ndarray:
        n = np.asarray(self.n_min).size
        return np.array([bool(r) for r in self.reasons], bool) if self.reasons else \
            np.zeros(n, bool)

    @property
    def bounds(self) -> ArtifactBounds:
        return ArtifactBounds(self.n_min, self.n_max, source="density test",
                              uncertain=self.uncertain, reasons=self.reasons)


def second_stage_params(joint: np.ndarray, bounds: ArtifactBounds | None = None
                        ) -> SecondStage:
    """Nmin, Nmax (the valid block, artifact excluded), Nth (min D2nd with P1st = 0) and
    PDM (min D2nd with P1st = 4), per TDC (section 3.2). -1 where a TDC saw nothing.
    ``bounds``: Nmin/Nmax found elsewhere (:func:`campaign_second_stage`); by default
    estimated from ``joint``. The estimate's ``uncertain`` reasons are kept."""
    b = estimate_bounds(joint.sum(axis=1)) if bounds is None else bounds
    d2 = np.arange(N_CODES_2ND)
    inside = (d2 >= b.n_min[:, None]) & (d2 <= b.n_max[:, None])

    def first(p1):
        seen = (joint[:, p1, :] > 0) & inside
        return np.where(seen.any(axis=1), np.argmax(seen, axis=1), -1)

    empty = joint.sum(axis=(1, 2)) == 0
    n_min = np.where(empty, -1, b.n_min)
    n_max = np.where(empty, -1, b.n_max)
    return SecondStage(n_min, n_max, first(0), first(4), tuple(b.reasons))


def campaign_second_stage(joints: list, cycles: list) -> SecondStage:
    """One set of second-stage parameters for a whole campaign of density tests.

    The bounds are the chip's, not the light's (section 3.4): the artifact comes at a
    fixed rate per cycle whatever the light (it stays when V_op is 0 V), while the valid
    block grows with the light. So the test whose block holds the most counts per code
    per cycle has the clearest block-to-artifact contrast; each TDC takes its bounds from
    that test among those whose estimate is not ``uncertain`` (from the densest with its
    reason where every one is), and every test is filtered with them. A dim test alone
    can be fooled: with the artifact at 2.7e-3 a cycle the artifact's D2nd codes at 0.02
    detections a cycle were as dense as the block's, the block ran to 255 unflagged
    (issue 15). Nth and PDM (the smallest D2nd at P1st 0 and
    4 inside the bounds) come from all the tests summed: the most cycles seen.

    ``joints``: each test's ``SecondStageAccumulator.counts`` (n_tdc, 8, 256);
    ``cycles``: each test's cycles.
    """
    joints = [np.asarray(j) for j in joints]
    if not joints:
        raise CalibrationError("campaign_second_stage: no density test")
    per = [estimate_bounds(j.sum(axis=1)) for j in joints]
    n_tdc = joints[0].shape[0]
    density = np.zeros((len(joints), n_tdc))
    for i, (j, b, c) in enumerate(zip(joints, per, cycles, strict=True)):
        d2 = j.sum(axis=1).astype(np.float64)
        width = (b.n_max.astype(np.int64) - b.n_min + 1).clip(1)
        density[i] = (d2 * b.in_block()).sum(axis=1) / width / max(float(c), 1.0)
    # an estimate the data cannot vouch for loses to any it can (a very bright test's
    # block can be cut where pile-up and its reset peak skew the D2nd codes: uncertain,
    # and then its narrow block looks the densest)
    certain = np.stack([~b.uncertain for b in per])
    pick = np.argmax(np.where(certain, density, density - np.inf), axis=0)
    pick = np.where(certain.any(axis=0), pick, np.argmax(density, axis=0))
    rows = np.arange(n_tdc)

    def chosen(field):
        return np.stack([getattr(b, field) for b in per])[pick, rows]

    reasons = np.array([b.reasons for b in per], dtype=object)[pick, rows]
    bounds = ArtifactBounds(chosen("n_min"), chosen("n_max"), source="density tests",
                            uncertain=chosen("uncertain"), reasons=tuple(reasons.tolist()))
    return second_stage_params(sum(joints[1:], joints[0].copy()), bounds)


# ------------------------------------------------------------------------- density test

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
               for f in ("lsb_s", "x_t", "width_lsb", "dnl_lsb", "inl_lsb", "inl_error_lsb")}
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
    out = {k: np.full(n_tdc, np.nan) for k in ("lsb", "x_t", "err")}
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
        out["lsb"][t], out["x_t"][t], widths[t], inl[t], out["err"][t] = res
    dnl = widths - 1.0
    return DensityResult(out["lsb"], out["x_t"], widths, dnl, inl, total, total / cycles, ok,
                         out["err"], tuple(reasons.tolist()))


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
                    _coates_var(h, at_risk) / scale ** 2, *fill, combine=combine,
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
    bound, tau_t, _ = peak(w)
    if not np.isfinite(tau_t):
        return None
    k = int(np.searchsorted(bound, tau_t, side="right") - 1)
    x_t = k + (tau_t - bound[k]) / w[k]
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
    return lsb, x_t, width, inl, err


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

    The variance of Coates' ``r w`` (:func:`_coates_var`) scaled to the width. A dead code
    (:func:`dead_codes`; its width 0) is measured too, to ``1 / R`` of ``r w`` (R cycles
    at risk, no count): a test that fills from this one then knows it has no width (given
    its phase mean instead, the codes under the reset peak and the table beyond the window
    would hold one code too many).
    """
    h = np.asarray(hits, np.float64)
    r = at_risk_by_code(h, cycles, artifacts)
    with np.errstate(divide="ignore", invalid="ignore"):
        per_rw = density.width_lsb / -np.log1p(-h / r)   # LSB per unit of r w
        var = _coates_var(h, r) * per_rw ** 2
    k = np.arange(N_CODES)[None, :]
    inside = (k < np.floor(density.x_t)[:, None] - EDGE_MARGIN - 1) & density.ok[:, None]
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
    pm = phase_mean[np.arange(N_CODES) % 8]
    # the phase mean's error as a fill: the scatter of the measured widths about it, less
    # what their own statistics explain
    stat = stat_var[interior]
    spread = (np.mean((w[interior] - pm[interior]) ** 2)
              - (np.mean(stat[np.isfinite(stat)]) if np.isfinite(stat).any() else 0.0))
    v_pm = max(spread, 1e-8)
    use = edge & np.isfinite(f) & np.isfinite(fv) & (fv > 0)
    out = w.copy()
    out[use] = (w[use] / v_pm + f[use] / fv[use]) / (1 / v_pm + 1 / fv[use])
    if loose is not None:
        out[use & loose] = f[use & loose]
    if combine:
        sv = np.full(w.size, np.nan)
        sv[interior] = stat_var[interior]
        both = (~edge & np.isfinite(f) & np.isfinite(fv) & (fv > 0) & np.isfinite(sv)
                & (sv > 0))
        out[both] = (w[both] / sv[both] + f[both] / fv[both]) / (1 / sv[both] + 1 / fv[both])
    return out


# ---------------------------------------------------------------- online LSB tracking

def signal_codes(hits: np.ndarray, dilate: int = 8, z: float = 6.0) -> np.ndarray:
    """(n_tdc, 512) mask of codes that hold more than uniform background: a range
    capture's returns (counts above a running median by ``z`` Poisson sigmas), widened by
    ``dilate`` codes on each side."""
    from scipy.ndimage import maximum_filter1d, median_filter

    h = np.asarray(hits, np.float64)
    base = median_filter(h, size=(1, 41), mode="nearest")
    peak = h > base + z * np.sqrt(np.maximum(base, 1.0))
    return maximum_filter1d(peak, size=2 * dilate + 1, axis=1)


#: The online LSB estimate of a TDC is not trusted when its own statistical error (the
#: reset peak's place over the background's widths: LSB x sqrt(1/6) / sqrt(hits)) exceeds
#: this, or when it lies further than ``TRACK_MAX_REL`` from the calibration's LSB at the
#: light (the density tests' LSBs span a few per cent over their light levels: a quarter
#: is a misplaced reset peak, never a drift).
TRACK_MAX_SIGMA_PS = 10.0
TRACK_MAX_REL = 0.25


@dataclass(frozen=True)
class Tracking:
    """The LSB measured from a range capture's background, against a calibration."""

    lsb_s: np.ndarray          #: measured now (NaN where the background is too thin)
    expected_s: np.ndarray     #: the calibration's LSB at this capture's light (eq. 5.1)
    light: float               #: detections per pixel per cycle of this capture
    hits: np.ndarray
    #: the estimate's own statistical error (NaN where not measured)
    sigma_s: np.ndarray | None = None
    #: per TDC why its estimate cannot be trusted ("" where it can, or was not measured)
    why: tuple = ()

    @property
    def flagged(self) -> np.ndarray:
        """TDCs whose estimate was measured but cannot be trusted (``why`` says why)."""
        n = int(np.asarray(self.lsb_s).size)
        return np.array([bool(w) for w in self.why] if self.why else [False] * n, bool)

    @property
    def drift_ps(self) -> np.ndarray:
        """Measured minus expected; NaN where not measured or not trusted (``flagged``)."""
        return np.where(self.flagged, np.nan, (self.lsb_s - self.expected_s) * 1e12)


def track_lsb(hits: np.ndarray, cycles: np.ndarray, window_s: float,
              expected_lsb_s: np.ndarray, min_hits: int = 1000,
              artifacts: np.ndarray | None = None) -> Tracking:
    """Measure each TDC's LSB from the uniform background of an ordinary range capture
    (its signal peaks masked) and compare it with what the calibration expects.
    ``artifacts``: the artifact words by code, where counted (see :func:`density_test`).
    A TDC's estimate is flagged (``why``, left out of ``drift_ps``) when its reset peak is
    not where the light ends (:func:`implausible_reset_peak`), its own error exceeds
    ``TRACK_MAX_SIGMA_PS``, or it is ``TRACK_MAX_REL`` or more from the expected LSB."""
    h = np.asarray(hits, np.float64)
    res = density_test(h, cycles, window_s, min_hits, exclude=signal_codes(h),
                       artifacts=artifacts)
    light = light_level(h, cycles)
    lsb = np.where(res.ok, res.lsb_s, np.nan)
    expected = np.broadcast_to(np.asarray(expected_lsb_s, np.float64), lsb.shape)
    sigma = lsb * INL_RMS_FACTOR / np.sqrt(np.maximum(res.hits, 1.0))
    why = implausible_reset_peak(h, res)
    for t in np.flatnonzero(np.isfinite(lsb) & (why == "")):
        ps, exp_ps = lsb[t] * 1e12, expected[t] * 1e12
        if sigma[t] * 1e12 > TRACK_MAX_SIGMA_PS:
            why[t] = (f"LSB {ps:.0f} +- {sigma[t] * 1e12:.0f} ps: uncertain beyond "
                      f"{TRACK_MAX_SIGMA_PS:g} ps")
        elif np.isfinite(exp_ps) and abs(ps / exp_ps - 1) >= TRACK_MAX_REL:
            why[t] = (f"LSB {ps:.0f} ps against {exp_ps:.0f} ps expected: implausible, not "
                      "a drift")
    return Tracking(lsb, np.asarray(expected_lsb_s), light, res.hits, sigma,
                    tuple(why.tolist()))


# ------------------------------------------------------------------- LSB against light

@dataclass(frozen=True)
class LsbFit:
    """LSB(n) per TDC (eq. 5.1's n): the measured LSBs at the density tests' light levels,
    interpolated, and the cubic in scaled x = (n - x_mean) / x_scale fitted to them.

    Inside the levels' range the LSB is a cubic spline through the measured points in
    sqrt(n) (:meth:`lsb_ps`): each point is measured to ~0.002 ps, while one cubic over
    0.02-0.75 detections a cycle leaves residuals of up to ~0.4 ps where the IR drop bends
    (the simulated chip saturates), and 0.1 ps of LSB is ~20 ps of range at mid-window.
    sqrt(n) spreads the flow's levels (roughly geometric) evenly, where the bend is, and a
    spline through them misses the simulated curve by <= 0.03 ps against 0.08 in n
    (benchmarks/range_accuracy.py). Outside the range, and without the points (an old
    calibration), the cubic, as eq. 5.1 has it.
    """

    coef: np.ndarray      #: (n_tdc, 4), c0 + c1 x + c2 x^2 + c3 x^3, in ps
    x_mean: float
    x_scale: float
    n_range: tuple[float, float]
    residual_ps: np.ndarray  #: (n_tdc, n_points)
    levels: np.ndarray | None = None  #: (n_points,) the light levels of the residuals
    #: the spline through the points, built on first use (the fit is read-only)
    _splines: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def cubic_ps(self, n) -> np.ndarray:
        """eq. 5.1's cubic at ``n``."""
        x = (np.asarray(n, np.float64) - self.x_mean) / self.x_scale
        return self.coef @ np.array([np.ones_like(x), x, x * x, x * x * x])

    def points_ps(self) -> np.ndarray:
        """(n_tdc, n_points) the measured LSBs: the cubic at the levels plus its residuals."""
        return self.cubic_ps(self.levels).reshape(self.coef.shape[0], -1) + np.asarray(
            self.residual_ps).reshape(self.coef.shape[0], -1)

    def lsb_ps(self, n) -> np.ndarray:
        n = np.asarray(n, np.float64)
        lv = None if self.levels is None else np.asarray(self.levels, np.float64)
        if lv is None or lv.size < 3 or n.ndim or not self.in_range(float(n)):
            return self.cubic_ps(n)
        if "lsb" not in self._splines:
            order = np.argsort(lv)
            lv, y = lv[order], self.points_ps()[:, order]
            # None: two tests at one light
            self._splines["lsb"] = RowSplines(lv, y) if np.all(np.diff(lv) > 0) else None
        spline = self._splines["lsb"]
        return self.cubic_ps(n) if spline is None else spline(float(n))

    def in_range(self, n) -> bool:
        lo, hi = self.n_range
        return bool(lo - 1e-12 <= n <= hi + 1e-12)


def _spline_rows(levels: np.ndarray, y: np.ndarray, n: float, coord=np.sqrt) -> np.ndarray:
    """Each row of ``y`` (n_rows, n_levels) read at light ``n`` by a cubic spline in
    ``coord(light)`` (sqrt: the time axis's) through its finite points (``levels``
    ascending). A row lacking a level (a TDC a density test flagged) uses the others: NaN
    (no time axis, flagged) where fewer than 3 remain or ``n`` lies outside the row's own
    levels."""
    return RowSplines(levels, y, coord)(n)


class RowSplines:
    """:func:`_spline_rows`'s splines, built once and read at any light (what depends on
    the calibration only is not rebuilt for every measurement)."""

    def __init__(self, levels: np.ndarray, y: np.ndarray, coord=np.sqrt):
        from scipy.interpolate import CubicSpline

        fin = np.isfinite(y)
        self.n_rows, self.coord, self.parts = y.shape[0], coord, []
        for pattern in np.unique(fin, axis=0):
            rows = np.all(fin == pattern, axis=1)
            lv = levels[pattern]
            if lv.size < 3:
                continue
            self.parts.append((rows, lv, bool(pattern.all()),
                               CubicSpline(coord(lv), y[rows][:, pattern].T, axis=0)))

    def __call__(self, n: float) -> np.ndarray:
        out = np.full(self.n_rows, np.nan)
        for rows, lv, complete, spline in self.parts:
            if not (complete or lv[0] - 1e-12 <= n <= lv[-1] + 1e-12):
                continue
            x = min(max(n, lv[0]), lv[-1])  # (the campaign's range is the caller's check)
            out[rows] = spline(self.coord(x))
        return out


def fit_lsb(n: np.ndarray, lsb_ps: np.ndarray) -> LsbFit:
    """Per-TDC cubic fit of LSB against light, on scaled x (well conditioned).

    ``n`` (n_points,) light levels, ``lsb_ps`` (n_tdc, n_points). Needs 4 distinct finite
    levels or more (:func:`stages.ranging.validation.check_levels`); with exactly 4 the
    cubic interpolates (residuals are zero and say nothing).
    """
    from stages.ranging.validation import check_levels

    n = np.asarray(n, np.float64)
    y = np.asarray(lsb_ps, np.float64)
    if n.size < 4:
        raise CalibrationError(f"an LSB-against-light fit needs density tests at >= 4 light "
                               f"levels (a cubic, eq. 5.1); found {n.size}")
    if y.ndim != 2 or y.shape[1] != n.size:
        raise CalibrationError(f"lsb_ps must be (TDCs, {n.size} light levels), found shape "
                               f"{y.shape}")
    if np.isfinite(y).any():  # (no TDC measured at all: the caller says why)
        n = check_levels(n)  # finite, >= 4 distinct: [.1, .1, .3, .3] gave half the LSB
    x_mean = float(n.mean())
    x_scale = float(n.std()) or 1.0
    x = (n - x_mean) / x_scale
    v = np.vander(x, 4, increasing=True)              # (n_points, 4), scaled: well posed
    fin = np.isfinite(y)
    coef = np.full((y.shape[0], 4), np.nan)
    # rows by which levels they have (a TDC a test flagged lacks that level): a cubic
    # through 4 or more, a quadratic through 3, nothing through fewer
    for pattern in np.unique(fin, axis=0):
        rows = np.all(fin == pattern, axis=1)
        m = int(np.unique(n[pattern]).size)  # distinct levels: a repeat adds no degree
        if m < 3:
            continue
        deg = min(m, 4)
        coef[rows] = 0.0
        coef[np.ix_(rows, np.arange(deg))] = np.linalg.lstsq(
            v[pattern][:, :deg], y[rows][:, pattern].T, rcond=None)[0].T
    resid = y - coef @ v.T
    return LsbFit(coef, x_mean, x_scale, (float(n.min()), float(n.max())), resid, n)


# ----------------------------------------------------------------- code -> time, delay

def histogram_sigma_s(hits: np.ndarray, density: DensityResult, lsb_s=None) -> np.ndarray:
    """Width (sigma) of each TDC's peak: the instrument response at zero distance. The
    background-subtracted counts of +-6 codes around the highest count (away from both
    window edges), at the code centres the density test gives."""
    lsb = density.lsb_s if lsb_s is None else np.asarray(lsb_s)
    centres = (np.arange(N_CODES)[None, :] + np.nan_to_num(density.inl_lsb)
               + 0.5 * (1 + np.nan_to_num(density.dnl_lsb))) * lsb[:, None]
    h = np.asarray(hits, np.float64)
    peak = np.argmax(h[:, 2:-8], axis=1) + 2
    win = np.abs(np.arange(N_CODES)[None, :] - peak[:, None]) <= 6
    w = np.where(win, np.clip(h - np.median(h, axis=1, keepdims=True), 0, None), 0.0)
    tau = (w * centres).sum(1) / np.maximum(w.sum(1), 1e-300)
    var = (w * (centres - tau[:, None]) ** 2).sum(1) / np.maximum(w.sum(1), 1e-300)
    # the centres quantise: remove a bin's uniform variance (LSB^2 / 12)
    return np.sqrt(np.maximum(var - lsb ** 2 / 12, 0.0))


def density_rows(density: DensityResult, rows) -> DensityResult:
    """The results of some TDCs (a worker's range)."""
    import dataclasses

    idx = np.arange(density.n_tdc)[rows]
    return DensityResult(**{f.name: getattr(density, f.name)[rows]
                            for f in dataclasses.fields(DensityResult) if f.name != "reasons"},
                         reasons=tuple(density.reasons[i] for i in np.atleast_1d(idx)))


def code_bounds(density: DensityResult) -> np.ndarray:
    """(n_tdc, 513) code boundaries in units of the density test's LSB (``k + INL_k``).
    Beyond the test's window (where it measured nothing) they continue one unit a code."""
    k = np.arange(N_CODES + 1, dtype=np.float64)
    inl = np.asarray(density.inl_lsb, np.float64)
    inl = np.concatenate([inl, inl[:, -1:]], axis=1)
    last = np.where(np.isfinite(inl), k[None, :], -1).max(axis=1)
    fill = np.take_along_axis(inl, np.maximum(last, 0)[:, None].astype(np.int64), axis=1)
    inl = np.where(np.isfinite(inl), inl, np.where(np.isfinite(fill), fill, 0.0))
    return k[None, :] + inl


def _bound_at(bounds: np.ndarray, x) -> np.ndarray:
    """Boundaries read at fractional codes ``x`` (n_tdc,), linearly within a code."""
    x = np.asarray(x, np.float64)
    good = np.isfinite(x)  # a dead or dark TDC has no LSB: NaN stays NaN
    x = np.clip(np.where(good, x, 0.0), 0, N_CODES - 1e-9)
    k = np.floor(x).astype(np.int64)[:, None]
    b0 = np.take_along_axis(bounds, k, axis=1)[:, 0]
    b1 = np.take_along_axis(bounds, k + 1, axis=1)[:, 0]
    return np.where(good, b0 + (x - k[:, 0]) * (b1 - b0), np.nan)


def scale_at_light(density: DensityResult, lsb_s, window_s: float,
                   fit: LsbFit | None = None, light: float | None = None,
                   splines: ScaleSplines | None = None, bounds=None) -> np.ndarray:
    """Seconds per unit of :func:`code_bounds` at a light whose LSB (the window over the
    code span, eq. 5.1's polynomial) is ``lsb_s``: tau = T falls at code ``x_T = T / lsb``,
    which is ``B(x_T)`` units of the density test's boundaries, so the scale is
    ``T / B(x_T)``. (``B(k) * lsb`` instead is off by ``tau INL(x_T) / x_T``: the density
    test's INL is zero at its own x_T only; ~60 ps at mid-window for 0.5 LSB.)

    With ``fit`` and ``light`` inside its levels, the scale itself is interpolated: each
    density test's measured LSB gives its scale ``T / B(T / LSB_i)``, and a cubic spline
    in sqrt(n) through those reads it at ``light``. The scale follows the VCOs' speed,
    smooth in the light; the window LSB does not: as x_T moves across codes it carries
    the INL there (``LSB = scale B(x_T) / x_T``), a ripple of ~0.1 ps (0.3 LSB of INL
    over 395 codes) that no smooth curve through the tests' LSBs follows, and 0.1 ps is
    ~20 ps of range at mid-window. ``splines`` (:func:`scale_splines`) and ``bounds``
    (:func:`code_bounds`): the same, built once for the calibration by the caller."""
    ok = np.asarray(density.ok, bool)
    if _interpolates(fit, light):
        splines = scale_splines(density, fit, window_s) if splines is None else splines
        return np.where(ok, splines.in_sqrt(float(light)), np.nan)
    x_t = window_s / np.asarray(lsb_s, np.float64)
    scale = window_s / _bound_at(code_bounds(density) if bounds is None else bounds, x_t)
    return np.where(ok, scale, np.nan)  # a dead TDC has no axis



def _interpolates(fit: LsbFit | None, light: float | None) -> bool:
    """Whether :func:`scale_at_light` interpolates the tests' scales at ``light``."""
    levels = None if fit is None or fit.levels is None else np.asarray(fit.levels, np.float64)
    return bool(levels is not None and light is not None and levels.size >= 3
                and fit.in_range(light) and np.unique(levels).size == levels.size)


def scale_points(density: DensityResult, fit: LsbFit, window_s: float):
    """The density tests' own scales: ``(levels, scales)``, the levels ascending and
    ``scales`` (n_tdc, n_levels) ``T / B(T / LSB_i)`` in seconds per unit of
    :func:`code_bounds` (NaN where a test flagged the TDC)."""
    bounds = code_bounds(density)
    levels = np.asarray(fit.levels, np.float64)
    order = np.argsort(levels)
    pts = fit.points_ps()[:, order] * 1e-12
    return levels[order], np.column_stack([window_s / _bound_at(bounds, window_s / pts[:, j])
                                           for j in range(pts.shape[1])])


@dataclass(frozen=True)
class ScaleSplines:
    """The density tests' scales (:func:`scale_points`) as splines in sqrt(n) and in n,
    built once for a calibration and a window (:func:`scale_splines`)."""

    levels: np.ndarray
    in_sqrt: RowSplines
    in_n: RowSplines


def _identity(v):
    return v


def scale_splines(density: DensityResult, fit: LsbFit, window_s: float) -> ScaleSplines:
    """What :func:`scale_at_light` and :func:`scale_spread` read at a light, built once."""
    levels, s_pts = scale_points(density, fit, window_s)
    return ScaleSplines(levels, RowSplines(levels, s_pts), RowSplines(levels, s_pts, _identity))


#: When the spread of the scale (:func:`scale_spread`, as ps at a return's tau) flags a
#: delay or a range: over this many of its statistical sigmas (INL x LSB, and for the
#: delay the peak's fit) plus the floor; half the chip sweep's tolerance (4 sigmas + 20
#: ps). Measured there: <= 27 ps on 35 healthy chips' zero-distance captures (sigma ~50
#: ps), 210-1000 ps where a fast-saturating LSB put the delay out of its tolerance.
LSB_SPREAD_SIGMAS, LSB_SPREAD_FLOOR_PS = 2.0, 20.0

def light_level(hits, cycles) -> float:
    """A measurement's light, detections per pixel per cycle (eq. 5.1's n): all its hits
    over its TDCs and its cycles."""
    h = np.asarray(hits)
    return float(h.sum() / (h.shape[0] * max(float(np.max(cycles)), 1.0)))


def scale_unresolved(spread, tau_s, density: DensityResult, sigma_s) -> np.ndarray:
    """Where the scale's spread (:func:`scale_spread`) at a return's ``tau_s`` is more
    than its timing allows: ``LSB_SPREAD_SIGMAS`` of its statistics (INL x LSB and the
    fit's ``sigma_s``) plus ``LSB_SPREAD_FLOOR_PS``. One rule for ``calibrate delay``'s
    flag and ``range``'s note."""
    allowed_ps = (LSB_SPREAD_SIGMAS * np.hypot(density.inl_error_lsb * density.lsb_s,
                                               np.asarray(sigma_s, np.float64)) * 1e12
                  + LSB_SPREAD_FLOOR_PS)
    with np.errstate(invalid="ignore"):
        return np.asarray(spread * np.asarray(tau_s, np.float64) * 1e12 > allowed_ps, bool)


def scale_spread(density: DensityResult, fit: LsbFit | None, window_s: float,
                 light: float, splines: ScaleSplines | None = None
                 ) -> tuple[np.ndarray, tuple[float, float]]:
    """How well the density tests' levels resolve the scale at ``light``: per TDC the
    relative difference between the scale :func:`scale_at_light` reads (a cubic spline in
    sqrt(n) through the tests' scales) and a cubic spline in n through the same points,
    and the two levels ``light`` lies between. NaN (and ``(nan, nan)``) where the scale
    is not interpolated at ``light`` (outside the levels: the caller's note already says).

    Both curves pass through every measured point; they part where the LSB bends
    between two levels faster than the points show, and there neither is to be trusted
    (issue 15: with four levels at 0.02-0.75 detections a cycle and an LSB that
    saturates by 0.15, they differ by 0.5-0.9 % of the scale at 0.24, where the sqrt(n)
    spline is off by 0.25-0.37 %: 170-250 ps of delay at tau = 68 ns). On chips the
    levels resolve (the chip zoo's n_sat >= 0.5) they differ by <= 0.04 % at the
    sweep's captures. The spread says where a curve is unresolved, not how far off
    it is (0.4-0.5 of the spread where the LSB saturates fast, up to ~3x a tiny spread
    elsewhere: the INL's noise in the points), so it flags, it does not correct.
    ``splines``: :func:`scale_splines` of the same, built once by the caller.
    """
    n_tdc = density.n_tdc
    if not _interpolates(fit, light):
        return np.full(n_tdc, np.nan), (float("nan"), float("nan"))
    splines = scale_splines(density, fit, window_s) if splines is None else splines
    levels = splines.levels
    in_sqrt = splines.in_sqrt(float(light))
    in_n = splines.in_n(float(light))
    i = int(np.clip(np.searchsorted(levels, light, side="right") - 1, 0, levels.size - 2))
    return np.abs(in_n / in_sqrt - 1), (float(levels[i]), float(levels[i + 1]))


#: Codes below where the light ends searched for the reset peak.
RESET_SEARCH = 4
#: Codes a return must keep from the reset peak for the in-situ fit to be trusted.
RESET_CLEARANCE = 12


def light_end(hits: np.ndarray, min_per_code: float = 1.0):
    """Where each TDC's uniform light ends: ``(top, step)``, ``top`` one past the last
    populated code, ``step`` True where light lies below it (a median of ``min_per_code``
    or more counts over the 30 codes 10-40 below). Nothing is detected at tau > T, so with
    ambient light the reset peak (tau = T) sits at the top; without it there is no step,
    and the last populated code is a return's tail."""
    h = np.asarray(hits)
    n = h.shape[1]
    populated = h.any(axis=1)
    top = np.where(populated, n - np.argmax(h[:, ::-1] > 0, axis=1), 0)
    lo, hi = np.maximum(top - 40, 0), np.maximum(top - 10, 0)
    level = np.zeros(h.shape[0])
    full = hi - lo == 30  # the 30 codes all on the axis: one median over those rows
    if full.any():
        codes = lo[full, None] + np.arange(30)
        level[full] = np.median(np.take_along_axis(h[full], codes, axis=1), axis=1)
    for i in np.flatnonzero(~full & (hi > lo)):  # light ending in the first 40 codes
        level[i] = np.median(h[i, lo[i]:hi[i]])
    return top, populated & (level >= min_per_code)


def scale_in_situ(hits: np.ndarray, cycles: np.ndarray, density: DensityResult,
                  window_s: float, returns: np.ndarray | None = None,
                  min_counts: float = 100.0, beyond: np.ndarray | None = None):
    """Seconds per unit of :func:`code_bounds` measured on a capture itself: its reset
    peak (tau = T) fitted over the density test's boundaries (:func:`fit_reset_peak`).

    Exact at the capture's own light, without the LSB polynomial; valid where the fitted
    codes are ones the density test measured (its own reset peak's codes are filled from
    the phase means): the capture brighter than the density test by ~15 codes of x_T.

    The reset peak is looked for where the capture's uniform light ends
    (:func:`light_end`: nothing is detected at tau > T), never simply as the highest
    count: a return near the window's beginning can be higher than the reset peak, and a
    dim capture's reset peak lies beyond the density test's. A TDC is declined, with the
    reason, where the capture has no ambient-light step (no reset peak to fit), where a
    return (``returns``: its code, NaN for none) lies within ``RESET_CLEARANCE`` codes of
    the reset peak (the fit would take the return for part of it), where the peak has
    fewer than ``min_counts`` counts, or where the density test did not measure those
    codes. ``beyond`` (a mask of TDCs): there any code the campaign measured will do
    (the table continued over the dimmer tests' codes, ``density_test(combine=True)``),
    so a capture between the tests' levels has its reset peak on measured codes too.

    Returns ``(scale, ok, reason)``; ``reason`` is "" where ``ok``.
    """
    h = np.asarray(hits, np.float64)
    n = h.shape[0]
    bounds = code_bounds(density)
    at_risk = at_risk_by_code(h, cycles)
    x_den = np.nan_to_num(density.x_t, nan=0.0)
    measured_to = np.floor(x_den) - EDGE_MARGIN - 1  # the density test's last measured code
    if beyond is not None:
        fin = np.isfinite(np.asarray(density.width_lsb, np.float64))
        last = np.where(fin.any(axis=1), N_CODES - 1 - np.argmax(fin[:, ::-1], axis=1), 0)
        measured_to = np.where(np.asarray(beyond, bool), np.maximum(last, measured_to),
                               measured_to)
    end, step = light_end(h)
    k = np.arange(N_CODES)[None, :]
    zone = (k >= end[:, None] - 1 - RESET_SEARCH) & (k < end[:, None])
    top = np.argmax(np.where(zone, h, -1), axis=1)
    # the uniform light per unit just below it (median of Coates' density: a target there
    # does not move it)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = -np.log1p(-np.clip(h / np.maximum(at_risk, 1.0), 0, 1 - 1e-12))
        per_unit = lam / np.diff(bounds, axis=1)
    band = (k >= top[:, None] - 60) & (k <= top[:, None] - 12)
    has_band = np.isfinite(np.where(band, per_unit, np.nan)).any(axis=1)
    u = np.nanmedian(np.where(band | ~has_band[:, None], per_unit, np.nan), axis=1)
    u = np.where(has_band & np.isfinite(u), u, 0.0)
    P, _, A = fit_reset_peak(h, at_risk, bounds, top, u)
    ret = np.full(n, np.nan) if returns is None else np.asarray(returns, np.float64)
    reason = np.full(n, "", dtype=object)
    checks = [  # the last that applies is the one given
        (top + RESET_HALF >= measured_to, "reset peak on codes the density test did not "
                                          "measure (capture not brighter than it)"),
        (np.abs(ret - top) <= RESET_CLEARANCE,
         f"a return within {RESET_CLEARANCE} codes of the reset peak"),
        (~(A >= min_counts), f"reset peak under {min_counts:g} counts"),
        (~np.isfinite(P), "reset peak fit failed"),
        (~step, "no ambient-light step (no reset peak to fit)"),
        (~np.asarray(density.ok, bool), "flagged by the density test"),
    ]
    for bad, why in checks:
        reason[bad] = why
    ok = reason == ""
    return np.where(ok, window_s / np.where(ok, P, 1.0), np.nan), ok, reason


def delay_s(t_laser_win_s: float, tau_peak_s) -> np.ndarray:
    """eq. 5.3: T_delay = T_Laser-Win - TDC_out * LSB (the zero-distance peak's tau)."""
    return t_laser_win_s - np.asarray(tau_peak_s, np.float64)


def distance_m(t_laser_win_s: float, delay, tau_s) -> np.ndarray:
    """eq. 5.4: distance = c/2 (T_Laser-Win - T_delay - TDC_out * LSB)."""
    from scipy.constants import c

    return c / 2 * (t_laser_win_s - np.asarray(delay) - np.asarray(tau_s))
