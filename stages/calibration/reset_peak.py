"""Calibration, the reset peak (tau = T): where the window ends on the code axis.

The LSB is the window over the code span (the issue's definition, and the one the
simulator's truth uses): ``LSB = T / x_T`` where ``x_T`` is where tau = T falls on the code
axis: the reset peak (a delta at T blurred by the TDC's jitter) fitted over the measured
code boundaries (:func:`fit_reset_peak`). INL_k = B_k / LSB - k at each code boundary B_k.
The cycles still at risk before each code (:func:`at_risk_by_code`) undo pile-up for the
density test and for this fit alike.
"""

from __future__ import annotations

import numpy as np

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
                   loglik: bool = False, p_var: bool = False):
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
    two sets of ``bounds`` for the same counts are compared by it. With ``p_var``, last,
    P's variance from the counts (the inverse of the Fisher information at the fit, its
    (P, P) element: s and A fitted too), in the units of ``bounds`` squared.
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

    def fisher(P, s, A):  # the model's Jacobian in (P, s, A), its mean, the information
        sc, za, zb, g, pa, pb, ya, yb, e, mu = model(P, s, A)
        jac = np.stack([A[:, None] * -(pb - pa) / sc + rk * e * u * (ndtr(ya) - ndtr(yb)),
                        A[:, None] * -(zb * pb - za * pa) / sc + rk * e * u * (pa - pb),
                        g], axis=-1)
        return jac, mu, np.einsum("nk,nki,nkj->nij", 1 / mu, jac, jac)

    for _ in range(iterations):
        jac, mu, info = fisher(P, s, A)
        score = np.einsum("nk,nki->ni", hk / mu - 1, jac)
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
    out = (P, s, A)
    if loglik:
        mu = model(np.nan_to_num(P), s, A)[-1]
        out += ((hk * np.log(mu) - mu).sum(1),)
    if p_var:
        info = fisher(np.nan_to_num(P), s, A)[2]
        with np.errstate(all="ignore"):
            ok = np.isfinite(info).all(axis=(1, 2)) & (np.linalg.det(info) > 0)
            cov = np.linalg.inv(np.where(ok[:, None, None], info, np.eye(3)[None]))
        out += (np.where(ok & np.isfinite(P), cov[:, 0, 0], np.nan),)
    return out
