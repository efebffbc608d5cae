"""Where the spatial estimator's relabelling starts (:func:`stages.ranging.spatial._relabel`,
step 3b): the frame's planes, and every pixel's label among them by a graph cut.

The relabelling's ICM sweeps are a local minimiser: they start from each undetected
pixel's own best candidate and move one pixel (or one run, in the block moves) at a
time. Where a pixel sees 2 signal photons among 50 of background, that start is noise,
and beside an edge that does not follow a row or a column the sweeps stop in a
staircase. Here the start is the labelling that minimises, over the whole frame,

    E = sum_p D_p(l_p) + CUT * (the length of the boundaries between labels)

with D_p the pixel's own Poisson negative log-likelihood ratio of each plane (the
Gaussian pulse over the bins, against its background) and the boundary's length
measured isotropically (Boykov & Kolmogorov 2003: a 16-neighbourhood whose edge weights
make a cut's cost the Euclidean length of the boundary to within a few per cent, at any
angle). Alpha-expansion (Boykov, Veksler & Zabih 2001) with a max-flow a label
(PyMaxflow: docs/decisions.md) finds a labelling within a known factor of the global
minimum. The labels are the frame's planes, found from the detected pixels' local fits
(:func:`planes`), and "no surface" (D = 0: the background alone).

A length prior rounds corners (a corner pixel costs more boundary than it saves), so
the labelling is only where the ICM starts; its line priors then keep the edges that
follow rows, columns and diagonals (docs/ranging.md has the numbers both ways), and
:func:`straight` puts a corner's pixel back with the straight edges beside it.
"""

from __future__ import annotations

import numpy as np

from stages.models.tcspc import log_phi_interval

CUT = 6.0          # nats a pixel of boundary length (seeds 1-8 at (2, 50): 3 and 10 worse)
CUT_CYCLES = 3     # expansion cycles over the labels (at most; it stops when none moves)
PLANE_MIN = 8      # detected returns a plane needs
PLANE_MAX = 40     # planes a frame at most
HYPOTHESES = 400   # the returns tried as a plane's seed, each round (an even subsample)
SUPPORT_PTS = 4000  # and the returns their support is counted on
HARD = 30.0        # nats: a label that cannot be (a detected pixel off it, no window)
PULSE_K = 4.0      # the likelihood's reach, +- sigmas of the pulse


def _even(idx: np.ndarray, k: int) -> np.ndarray:
    """At most ``k`` of ``idx``, evenly spaced (deterministic: no generator needed)."""
    return idx if idx.size <= k else idx[np.linspace(0, idx.size - 1, k).astype(np.int64)]


def planes(tb, slope, det, sig_cnt, sig_out, tol):
    """The frame's planes t = a0 + a1 r + a2 c (bins) from its detected returns: the
    return whose local plane (its time and slopes) has the most returns within ``tol``
    seeds a plane; a least-squares fit on those within ``tol`` of it, refitted as it
    grows (a local plane's slope is off by a little, which far away is a lot); its
    returns leave; again, while a plane has ``PLANE_MIN``. Returns a list of (a (3,),
    signal a pixel, sigma (s)): the medians over its returns."""
    r, c, k = np.nonzero(det & np.isfinite(tb))
    t = tb[r, c, k]
    s0, s1 = slope[r, c, k, 0], slope[r, c, k, 1]
    rf, cf = r.astype(np.float64), c.astype(np.float64)
    left = np.ones(r.size, bool)
    out = []
    while left.sum() >= PLANE_MIN and len(out) < PLANE_MAX:
        idx = np.nonzero(left)[0]
        hyp, pts = _even(idx, HYPOTHESES), _even(idx, SUPPORT_PTS)
        pred = (t[hyp, None] + s0[hyp, None] * (rf[None, pts] - rf[hyp, None])
                + s1[hyp, None] * (cf[None, pts] - cf[hyp, None]))
        sup = (np.abs(pred - t[None, pts]) < tol).sum(1)
        if sup.max() * idx.size / pts.size < PLANE_MIN:
            break
        b = hyp[np.argmax(sup)]
        a = np.array([t[b] - s0[b] * rf[b] - s1[b] * cf[b], s0[b], s1[b]])
        for _ in range(6):
            inl = idx[np.abs(t[idx] - (a[0] + a[1] * rf[idx] + a[2] * cf[idx])) < tol]
            X = np.stack([np.ones(inl.size), rf[inl], cf[inl]], 1)
            if inl.size < 3 or np.linalg.matrix_rank(X) < 3:
                break
            a = np.linalg.lstsq(X, t[inl], rcond=None)[0]
        inl = idx[np.abs(t[idx] - (a[0] + a[1] * rf[idx] + a[2] * cf[idx])) < tol]
        left[b] = False
        if inl.size < PLANE_MIN:
            continue
        left[inl] = False
        out.append((a, float(np.median(sig_cnt[r[inl], c[inl], k[inl]])),
                    float(np.median(sig_out[r[inl], c[inl], k[inl]]))))
    return out


def gauss_llr(P0, beta, T, S, sb, shape=None):
    """Each pixel's Poisson log-likelihood ratio of a surface at ``T`` (h, w, L; bins,
    NaN: none) with ``S`` (L,) signal photons against its background alone (``beta``
    (h, w) a bin, times ``shape`` (bins,) the background's profile, None: flat): the
    Gaussian pulse (sigma ``sb`` bins) integrated over each bin within +-``PULSE_K``
    sigma; ``P0`` (h, w, bins + 1) the counts' prefix sums. -inf where the pulse lies
    mostly outside the window."""
    h, w, n = P0.shape[0], P0.shape[1], P0.shape[2] - 1
    reach = int(np.ceil(PULSE_K * sb)) + 1
    ok = np.isfinite(T)
    ti = np.where(ok, T, -1e6)
    base = np.floor(ti).astype(np.int64)
    acc = np.zeros(T.shape)
    mass = np.zeros(T.shape)
    for d in range(-reach, reach + 1):
        j = base + d
        inside = (j >= 0) & (j < n)
        jc = np.clip(j, 0, n - 1)
        p = np.exp(log_phi_interval((j - ti) / sb, (j + 1 - ti) / sb))
        jf = jc.reshape(h, w, -1)
        m = (np.take_along_axis(P0, jf + 1, -1) - np.take_along_axis(P0, jf, -1)).reshape(T.shape)
        bg = beta[..., None] * (1.0 if shape is None else shape[jc])
        acc += np.where(inside, m * np.log1p(S * p / np.maximum(bg, 1e-12)), 0.0)
        mass += np.where(inside, p, 0.0)
    return np.where(ok & (mass > 0.5), acc - S * mass, -np.inf)


def _pairs(h, w):
    """The 16-neighbourhood's edges, each once: (di, dj, weight) with the weight
    (pi / 16) / |e| that makes a cut's cost its boundary's Euclidean length. A line of
    pixels (one row or one column): its one neighbour each way, a cut costing 1."""
    if h == 1 or w == 1:
        return [(0, 1, 1.0)] if w > 1 else [(1, 0, 1.0)] if h > 1 else []
    half = [(0, 1), (1, 0), (1, 1), (1, -1), (1, 2), (2, 1), (1, -2), (2, -1)]
    return [(i, j, np.pi / 16.0 / np.hypot(i, j)) for i, j in half if i < h and abs(j) < w]


def _sl(i, j, h, w):
    """The slices of p and of its neighbour q = p + (i, j) over the pairs inside."""
    return ((slice(max(-i, 0), h - max(i, 0)), slice(max(-j, 0), w - max(j, 0))),
            (slice(max(i, 0), h - max(-i, 0)), slice(max(j, 0), w - max(-j, 0))))


def expand(D: np.ndarray, lam: float = CUT, cycles: int = CUT_CYCLES) -> np.ndarray:
    """Alpha-expansion of E = sum_p D[p, l_p] + lam * (boundary length) (Potts, the
    16-neighbourhood's weights). ``D`` (h, w, L) costs (finite). Returns the labels
    (h, w). Each move is a max-flow (the Kolmogorov-Zabih construction; the Potts term
    is a metric, so each is exact) and is kept only where it lowers E."""
    import maxflow

    h, w, L = D.shape
    lab = np.argmin(D, -1)
    ids = np.arange(h * w).reshape(h, w)
    pairs = [(_sl(i, j, h, w), lam * wt) for i, j, wt in _pairs(h, w)]

    def energy(lb):
        e = float(np.take_along_axis(D, lb[..., None], -1).sum())
        for (sp, sq), wt in pairs:
            e += wt * float((lb[sp] != lb[sq]).sum())
        return e

    E = energy(lab)
    for _ in range(cycles):
        moved = False
        for al in range(L):
            cur = np.take_along_axis(D, lab[..., None], -1)[..., 0]
            c1 = D[..., al] - cur                 # the cost of taking al, less of keeping
            ei, ej, ec = [], [], []
            for (sp, sq), wt in pairs:
                a, b = lab[sp], lab[sq]
                A, B, C = wt * (a != b), wt * (a != al), wt * (b != al)
                # E(xp, xq) = A + (C - A) xp - C xq + (B + C - A) (1 - xp) xq
                c1[sp] += C - A
                c1[sq] -= C
                ei.append(ids[sp].ravel())
                ej.append(ids[sq].ravel())
                ec.append((B + C - A).ravel())
            ei, ej, ec = np.concatenate(ei), np.concatenate(ej), np.concatenate(ec)
            keep = ec > 0
            g = maxflow.Graph[float](h * w, int(keep.sum()))
            g.add_nodes(h * w)
            g.add_edges(ei[keep], ej[keep], ec[keep], np.zeros(int(keep.sum())))
            d = c1.ravel()
            g.add_grid_tedges(np.arange(h * w), np.maximum(d, 0.0), np.maximum(-d, 0.0))
            g.maxflow()
            take = g.get_grid_segments(np.arange(h * w)).reshape(h, w)
            new = np.where(take, al, lab)
            En = energy(new)
            if En < E - 1e-9:
                lab, E, moved = new, En, True
        if not moved:
            break
    return lab


def start(tb, slope, det, sig_cnt, sig_out, P0, beta, sb, prof=None):
    """Every pixel's plane by the cut (above): (T (h, w) its time, bins, NaN for no
    surface or no plane; (h, w, 2) slopes; signal a pixel; sigma (s); and the planes:
    their times (h, w, L) at every pixel, coefficients (L, 3), signal (L,) and sigma
    (L,)), or None where the frame has no plane. A detected pixel's labels are its
    detections' planes (those within ``3 sb`` of one cost 0, the others ``HARD``); where
    none is, its photons'."""
    h, w, nc = tb.shape
    tol = 3.0 * sb
    pl = planes(tb, slope, det, sig_cnt, sig_out, tol)
    if not pl:
        return None
    a = np.array([p[0] for p in pl])                                  # (L, 3)
    rr, cc = np.mgrid[0:h, 0:w].astype(np.float64)
    T = a[:, 0] + a[:, 1] * rr[..., None] + a[:, 2] * cc[..., None]    # (h, w, L)
    S = np.array([max(p[1], 0.05) for p in pl])
    llr = gauss_llr(P0, beta, T, S, sb, None if prof is None else prof[0])
    D = np.minimum(np.where(np.isfinite(llr), -llr, HARD), HARD)
    near = (np.abs(T[..., :, None] - np.where(det, tb, np.nan)[..., None, :]) < tol).any(-1)
    fixed = near.any(-1)
    D = np.where(fixed[..., None], np.where(near, 0.0, HARD), D)
    D = np.concatenate([D, np.where(fixed, HARD, 0.0)[..., None]], -1)  # no surface
    lab = expand(D)
    on = lab < len(pl)
    k = np.minimum(lab, len(pl) - 1)
    t = np.where(on, np.take_along_axis(T, k[..., None], -1)[..., 0], np.nan)
    sl = np.where(on[..., None], a[k][..., 1:], 0.0)
    sg = np.array([p[2] for p in pl])
    return (t, sl, np.where(on, S[k], 0.0), np.where(on, sg[k], np.inf), (T, a, S, sg))


# corners (:func:`straight`, called by stages.ranging.spatial._corners)
STRAIGHT_R = 3         # a window is (2 R + 1)^2 pixels
STRAIGHT_SHIFT = 3     # centred on the pixel, or on p + (i, j), i, j in {-SHIFT, 0, SHIFT}
STRAIGHT_ANGLES = 36   # the boundary's directions tried, over 180 degrees
STRAIGHT_MIN = 6.0     # the weight of each label a window needs
STRAIGHT_FREE = 0.5    # an undetected pixel's weight (a detected one's: 1)
STRAIGHT_CORNER = 0.5  # the centred window's misfit from which the pixel may be a corner
STRAIGHT_MISFIT = 0.5  # and a window beside it misfits at most this
CORNER_NATS = 2.0      # the pixel's own log-likelihood a corner's label may cost
CORNER_PASSES = 2


def _straight_tables():
    """Per window (the centred one first): its offsets from p (p itself left out), their
    order along each direction's normal, the gaps between consecutive projections,
    whether p (at 0) lies below each split between them, and the gaps' tie-breaker."""
    R, K, sh = STRAIGHT_R, STRAIGHT_ANGLES, STRAIGHT_SHIFT
    th = np.arange(K) * np.pi / K
    nrm = np.stack([np.sin(th), np.cos(th)], -1)                  # (K, 2)
    out = []
    for si, sj in [(0, 0)] + [(i, j) for i in (-sh, 0, sh) for j in (-sh, 0, sh) if i or j]:
        di, dj = np.mgrid[si - R:si + R + 1, sj - R:sj + R + 1]
        keep = (di != 0) | (dj != 0)
        off = np.stack([di[keep], dj[keep]], -1)                  # (M, 2)
        proj = nrm @ off.T.astype(np.float64)                     # (K, M)
        order = np.argsort(proj, -1, kind="stable")
        sp = np.take_along_axis(proj, order, -1)
        gap = np.diff(sp, axis=-1)                                # (K, M - 1)
        # the widest gap among equal misfits; a split between equal projections (no gap:
        # the pixel's side there is not defined) never chosen
        tie = np.where(gap > 1e-9, 1e-3 * gap, -np.inf)
        tie = np.tile(tie, (2, 1)).ravel().astype(np.float32)
        out.append((off, order, gap, 0.5 * (sp[:, 1:] + sp[:, :-1]) > 0.0, tie))
    return out


_STRAIGHT = None


def _split(cat, weight, who, A, B, win):
    """One window's best half-plane between A and B for each pixel of ``who``: (the
    label it puts the pixel on, its misfit, its gap, whether the window holds enough of
    both)."""
    off, order, gap, p_below, tie = win
    h, w = cat.shape
    n = who.shape[0]
    r = who[:, 0, None] + off[:, 0]
    c = who[:, 1, None] + off[:, 1]
    ins = (r >= 0) & (r < h) & (c >= 0) & (c < w)
    rc, cc = np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)
    cw = np.where(ins, cat[rc, cc], -1)
    wt = np.where(ins, weight[rc, cc], 0.0)
    # (float32: the weights are halves and ones, their sums exact)
    a = np.where(cw == A[:, None], wt, 0.0).astype(np.float32)   # (n, M)
    b = np.where(cw == B[:, None], wt, 0.0).astype(np.float32)
    at, bt = a.sum(1), b.sum(1)
    enough = (at >= STRAIGHT_MIN) & (bt >= STRAIGHT_MIN)
    ca = np.cumsum(a[:, order], -1)[..., :-1]                     # (n, K, M - 1): below
    cb = np.cumsum(b[:, order], -1)[..., :-1]
    m1 = (at[:, None, None] - ca) + cb                            # A below, B above
    m2 = ca + (bt[:, None, None] - cb)                            # B below, A above
    both = np.concatenate([m1, m2], 1).reshape(n, -1)
    k = np.argmin(both - tie, -1)                                 # the widest gap among equals
    mis = both[np.arange(n), k]
    first = k < gap.size                                          # m1: A below
    kk = k % gap.size
    below = p_below.ravel()[kk]
    return (np.where(below == first, A, B), mis, gap.ravel()[kk], enough)


def straight(cat, weight, who, corner=None):
    """Each pixel of ``who`` (n, 2): the label its neighbours' straight boundaries put it
    on, where the window centred on it is not one straight boundary (misfit >=
    ``corner``, default ``STRAIGHT_CORNER``). ``cat`` (h, w) the labels (-1: none),
    ``weight`` (h, w) each pixel's say. In each of the 8 windows centred beside the
    pixel, the half-plane (36 directions) splitting the pixel's label A from the
    commonest other label B near it with the least weight on the wrong side, the widest
    gap between the two among equals; a window with ``STRAIGHT_MIN`` of each and a
    misfit of at most ``STRAIGHT_MISFIT`` is one straight boundary, and the side of it
    the pixel lies on is its say. A corner pixel lies inside both edges' windows; one
    beyond the end of an edge lies on the extension of one and outside the other: the
    windows that are straight must agree. Returns (label (n,), -1 where no window is
    straight or they differ; the least misfit among them, inf where none)."""
    global _STRAIGHT
    corner = STRAIGHT_CORNER if corner is None else corner
    if _STRAIGHT is None:
        _STRAIGHT = _straight_tables()
    h, w = cat.shape
    n = who.shape[0]
    pred = np.full(n, -1)
    best = np.full(n, np.inf)
    L = int(cat.max()) + 1
    if L <= 0 or n == 0:
        return pred, best
    A = cat[who[:, 0], who[:, 1]]
    reach = STRAIGHT_R + STRAIGHT_SHIFT
    di, dj = np.mgrid[-reach:reach + 1, -reach:reach + 1]
    r, c = who[:, 0, None] + di.ravel(), who[:, 1, None] + dj.ravel()
    ins = (r >= 0) & (r < h) & (c >= 0) & (c < w)
    cc = np.where(ins, cat[np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)], -1)
    ww = np.where(ins, weight[np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)], 0.0)
    ok = (cc >= 0) & (cc != A[:, None])
    hist = np.zeros((n, L))
    np.add.at(hist, (np.nonzero(ok)[0], cc[ok]), ww[ok])
    B = np.argmax(hist, -1)
    _, cen, _, enough = _split(cat, weight, who, A, B, _STRAIGHT[0])
    sub = np.nonzero(~enough | (cen >= corner))[0]                # not one straight edge
    if not sub.size:
        return pred, best
    said = np.full(sub.size, -1)                                  # the straight windows'
    split = np.zeros(sub.size, bool)                              # label, unless they differ
    for win in _STRAIGHT[1:]:
        lab, mis, _, en = _split(cat, weight, who[sub], A[sub], B[sub], win)
        ok = en & (mis <= STRAIGHT_MISFIT)
        split |= ok & (said >= 0) & (said != lab)
        said = np.where(ok, lab, said)
        best[sub] = np.where(ok, np.minimum(mis, best[sub]), best[sub])
    pred[sub] = np.where(split, -1, said)
    return pred, best
