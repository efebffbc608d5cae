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
:func:`edge_side` puts each pixel beside a boundary on the side of the straight edge
that the photons of the window around it, or of the windows beside it, place.
"""

from __future__ import annotations

import numpy as np

from stages.models.tcspc import log_phi_intervals
from stages.ranging._numba import numba

CUT = 6.0          # nats a pixel of boundary length (seeds 1-8 at (2, 50): 3 and 10 worse)
CUT_CYCLES = 3     # expansion cycles over the labels (at most; it stops when none moves)
PLANE_MIN = 8      # detected returns a plane needs
PLANE_MAX = 40     # planes a frame at most
HYPOTHESES = 400   # the returns tried as a plane's seed, each round (an even subsample)
SUPPORT_PTS = 4000  # and the returns their support is counted on
HARD = 30.0        # nats: a label that cannot be (a detected pixel off it, no window)
PULSE_K = 4.0      # the likelihood's reach, +- sigmas of the pulse


def _in_parts(n: int, parts: int, run) -> list:
    """``run(slice)`` over ``parts`` consecutive slices of ``range(n)``, on as many
    threads (for work that releases the GIL); their results in order."""
    from concurrent.futures import ThreadPoolExecutor

    cut = np.linspace(0, n, parts + 1).astype(np.int64)
    with ThreadPoolExecutor(parts) as ex:
        return list(ex.map(run, [slice(a, b) for a, b in zip(cut[:-1], cut[1:], strict=True)]))


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


def gauss_llr(P0, beta, T, S, sb, shape=None, threads=1):
    """Each pixel's Poisson log-likelihood ratio of a surface at ``T`` (h, w, L; bins,
    NaN: none) with ``S`` (L,) signal photons against its background alone (``beta``
    (h, w) a bin, times ``shape`` (bins,) the background's profile, None: flat): the
    Gaussian pulse (sigma ``sb`` bins) integrated over each bin within +-``PULSE_K``
    sigma; ``P0`` (h, w, bins + 1) the counts' prefix sums. -inf where the pulse lies
    mostly outside the window. ``threads`` > 1: bands of rows at once (numpy and
    scipy's ufuncs release the GIL; the same numbers)."""
    parts = min(max(int(threads), 1), P0.shape[0] // 8)
    if parts > 1:
        return np.concatenate(_in_parts(
            P0.shape[0], parts, lambda k: gauss_llr(P0[k], beta[k], T[k], S, sb, shape)))
    h, w, n = P0.shape[0], P0.shape[1], P0.shape[2] - 1
    reach = int(np.ceil(PULSE_K * sb)) + 1
    ok = np.isfinite(T)
    ti = np.where(ok, T, -1e6)
    base = np.floor(ti).astype(np.int64)
    acc = np.zeros(T.shape)
    mass = np.zeros(T.shape)
    # each bin's share of the pulse (every bin edge's log_ndtr once)
    ds = np.arange(-reach, reach + 2).reshape((-1,) + (1,) * T.ndim)
    share = np.exp(log_phi_intervals((base + ds - ti) / sb))
    for d in range(-reach, reach + 1):
        j = base + d
        inside = (j >= 0) & (j < n)
        jc = np.clip(j, 0, n - 1)
        p = share[d + reach]
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


def start(tb, slope, det, sig_cnt, sig_out, P0, beta, sb, prof=None, seen=None, threads=1):
    """Every pixel's plane by the cut (above): (its index (h, w), -1 for no surface; and
    the planes: their times (h, w, L) at every pixel, bins, coefficients (L, 3), signal
    (L,), sigma (L,) and each pixel's Poisson log-likelihood ratio of each (h, w, L)), or
    None where the frame has no plane. A detected pixel's labels are its
    detections' planes (those within ``3 sb`` of one cost 0, the others ``HARD``); where
    none is, its photons'. ``seen`` (default ``det``): the detections the planes are
    found from. ``threads``: :func:`gauss_llr`'s."""
    h, w, nc = tb.shape
    tol = 3.0 * sb
    pl = planes(tb, slope, det if seen is None else seen, sig_cnt, sig_out, tol)
    if not pl:
        return None
    a = np.array([p[0] for p in pl])                                  # (L, 3)
    rr, cc = np.mgrid[0:h, 0:w].astype(np.float64)
    T = a[:, 0] + a[:, 1] * rr[..., None] + a[:, 2] * cc[..., None]    # (h, w, L)
    S = np.array([max(p[1], 0.05) for p in pl])
    llr = gauss_llr(P0, beta, T, S, sb, None if prof is None else prof[0], threads)
    D = np.minimum(np.where(np.isfinite(llr), -llr, HARD), HARD)
    near = (np.abs(T[..., :, None] - np.where(det, tb, np.nan)[..., None, :]) < tol).any(-1)
    fixed = near.any(-1)
    D = np.where(fixed[..., None], np.where(near, 0.0, HARD), D)
    D = np.concatenate([D, np.where(fixed, HARD, 0.0)[..., None]], -1)  # no surface
    lab = expand(D)
    sg = np.array([p[2] for p in pl])
    return np.where(lab < len(pl), lab, -1), (T, a, S, sg, llr)


# edges (:func:`edge_side`, called by stages.ranging.spatial._edges)
EDGE_R = 5           # the window is (2 R + 1)^2 pixels, centred on the pixel
EDGE_ANGLES = 36     # the boundary's directions tried, over 180 degrees (both ways round)
EDGE_CAP = 6.0       # nats: an undetected pixel's say between two planes at most
EDGE_DET = 12.0      # and a detected pixel's, for the plane it is on
EDGE_MIN = 6.0       # the weight of each label a window needs
EDGE_FREE = 0.5      # an undetected pixel's weight (a detected one's: 1)
EDGE_MISFIT = 2.0    # the labels' misfit (weights as EDGE_FREE) of a straight window
EDGE_P = 0.7         # the posterior of the other side from which the pixel moves
EDGE_PASSES = 3       # at most (it stops when none moves)
EDGE_SHIFT = 5       # the windows beside the pixel: centred this far along rows, columns
EDGE_BESIDE_SPAN = 1  # and each weighs the lines within this many directions of its best
EDGE_PART = 64       # pixels a thread at least (fewer: one thread)
EDGE_TURN = 4        # directions (20 degrees) between two windows' lines that are a corner


def _edge_table(si: int, sj: int):
    """The window centred at (si, sj) from p: its offsets from p, their order along each
    direction's normal, log of the gaps between consecutive projections (-inf: no gap)
    and whether p lies below each split."""
    R, K = EDGE_R, EDGE_ANGLES
    th = np.arange(K) * np.pi / K
    nrm = np.stack([np.sin(th), np.cos(th)], -1)
    di, dj = np.mgrid[si - R:si + R + 1, sj - R:sj + R + 1]
    off = np.stack([di.ravel(), dj.ravel()], -1)
    proj = nrm @ off.T.astype(np.float64)
    order = np.argsort(proj, -1, kind="stable")
    sp = np.take_along_axis(proj, order, -1)
    gap = np.diff(sp, axis=-1)
    lg = np.where(gap > 1e-9, np.log(np.maximum(gap, 1e-300)), -np.inf)
    return off, order, lg, 0.5 * (sp[:, 1:] + sp[:, :-1]) > 0.0, (si, sj)


def _edge_tables():
    """Per window (the centred one first, then those centred ``EDGE_SHIFT`` beside p)
    its :func:`_edge_table`."""
    sh = EDGE_SHIFT
    return [_edge_table(si, sj)
            for si, sj in [(0, 0)] + [(i, j) for i in (-sh, 0, sh) for j in (-sh, 0, sh)
                                      if i or j]]


_EDGE = None


def _edge_windows():
    """The windows' tables for the constants as they are (built again if they change)."""
    global _EDGE
    key = (EDGE_R, EDGE_ANGLES, EDGE_SHIFT)
    if _EDGE is None or _EDGE[0] != key:
        tables = _edge_tables()
        _EDGE = (key, tables, {(0, 0): tables[0]})  # (and those moved in, by centre)
    return _EDGE[1]


def _inside(who, shape):
    """Each pixel's own window's centre from it, (n, 2): (0, 0), or moved in from the
    image's border until the window lies inside (along an axis the image is shorter than
    the window: not moved)."""
    R = EDGE_R
    out = np.zeros(who.shape, np.int64)
    for k, n in enumerate(shape):
        if n >= 2 * R + 1:
            out[:, k] = np.clip(who[:, k], R, n - 1 - R) - who[:, k]
    return out


def _own_window(cat, weight, det, llr, who, A, B, compiled=None, threads=1):
    """The posterior of each pixel's own window (:func:`_edge_window`): centred on it,
    or moved in from the image's border so that it holds all its (2 R + 1)^2 pixels.
    At the border a window cut short has one end: a line turned a step off the edge
    cuts off the few pixels at its end, and their own photons decide it (seed 12 at (2,
    50): the floor's first row at the image's left border, three pixels put on the wall
    at 0.91-0.96)."""
    _edge_windows()
    moved = _EDGE[2]
    shift = _inside(who, cat.shape)
    post = np.full(who.shape[0], np.nan)
    keys, inv = np.unique(shift, axis=0, return_inverse=True)
    for g, (si, sj) in enumerate(keys):
        key = (int(si), int(sj))
        if key not in moved:
            moved[key] = _edge_table(*key)
        win = moved[key]
        k = np.nonzero(inv.ravel() == g)[0]
        post[k] = _edge_window(cat, weight, det, llr, who[k], A[k], B[k], win, compiled,
                               threads)[0]
    return post


def edge_side(cat, weight, det, llr, who, A, B, compiled=None, threads=1):
    """Each pixel of ``who`` (n, 2) on a straight boundary between the planes ``A`` and
    ``B`` (n,): the posterior that it lies on B's side (NaN: no say). A window is one
    straight boundary where its labels ``cat`` (h, w; -1 none) weighted by ``weight``
    split between A and B along a half-plane with a misfit of at most ``EDGE_MISFIT``.
    In such a window every half-plane (``EDGE_ANGLES`` directions, both ways round,
    every split between the pixels' projections, a uniform prior over the line's offset:
    the gap's width) is weighed by the likelihood of the window's photons with A on one
    side and B on the other: each undetected pixel's Poisson log-likelihood ratio of A
    against B (``llr`` (h, w, L), each plane's, clipped to +-``EDGE_CAP``), each
    detected pixel +-``EDGE_DET`` for the plane it is on. The edge's pixels far along it
    place it where each one's few photons cannot. The pixel's own window has the say
    where it is straight: centred on it, or moved in from the image's border until it
    lies inside (:func:`_own_window`). Else the windows centred ``EDGE_SHIFT`` beside
    it that are straight, each over the lines within ``EDGE_BESIDE_SPAN`` directions of
    its best line's (lines far off it weigh little each, but there are many, and near a
    corner they turn towards the other edge), where they all agree (each beyond
    ``EDGE_P`` the same way) and two of them place it: their lines ``EDGE_TURN``
    directions apart (a corner's two edges), or on both sides of it along each one's
    line, each centre a pixel or more from it (a run of wrong labels between them); not
    one edge's windows on one side only (beyond the edge's end). ``compiled``: by numba
    (None: where it is installed; False: the numpy twin, in chunks of 512 pixels);
    ``threads`` > 1: numba's pixels in that many parts at once (the kernel releases the
    GIL; the same numbers)."""
    tables = _edge_windows()
    post = _own_window(cat, weight, det, llr, who, A, B, compiled, threads)
    rest = np.nonzero(np.isnan(post))[0]
    if not rest.size or not EDGE_SHIFT:
        return post
    said = [_edge_window(cat, weight, det, llr, who[rest], A[rest], B[rest], win, compiled,
                         threads, EDGE_BESIDE_SPAN)
            for win in tables[1:]]
    P = np.stack([x[0] for x in said], 1)                         # (m, 8)
    kd = np.stack([x[1] for x in said], 1)
    ok = np.isfinite(P)
    lo, hi = np.fmin.reduce(P, 1), np.fmax.reduce(P, 1)
    agree = ok.any(1) & ((lo > EDGE_P) | (hi < 1.0 - EDGE_P))
    # two straight windows with lines EDGE_TURN apart (a corner's two edges), or along
    # one line on both sides of the pixel (a run of wrong labels between them); not one
    # edge's windows on one side only (beyond its end)
    K = EDGE_ANGLES
    th = kd * np.pi / K
    placed = np.zeros(rest.size, bool)
    cen = np.array([win[4] for win in tables[1:]], np.float64)    # (8, 2)
    # each window's centre along each window's line (the tangent (cos, -sin) in (row,
    # col)); a centre within a pixel of p along it (across the line from p) is on
    # neither side
    along = (cen[None, :, None, 0] * np.cos(th)[:, None, :]
             - cen[None, :, None, 1] * np.sin(th)[:, None, :])   # (m, window, line)
    side = np.where(np.abs(along) >= 1.0, np.sign(along), 0.0)
    for i in range(len(said)):
        for j in range(i + 1, len(said)):
            both = ok[:, i] & ok[:, j]
            turn = np.abs(kd[:, i] - kd[:, j])
            turn = np.minimum(turn, K - turn)
            # on both sides of p along either window's line (lines within EDGE_TURN)
            across = ((side[:, i, i] * side[:, j, i] < 0)
                      & (side[:, i, j] * side[:, j, j] < 0))
            placed |= both & ((turn >= EDGE_TURN) | across)
    post[rest] = np.where(agree & placed, np.where(lo > EDGE_P, lo, hi), np.nan)
    return post


def _edge_window(cat, weight, det, llr, who, A, B, win, compiled=None, threads=1,
                 span=None):
    """:func:`edge_side` in one window: the posterior, NaN where it is not straight (by
    numba where it is installed, ``compiled`` None or True, its pixels in ``threads``
    parts at once; the numpy twin else), and its best line's direction. ``span``: over
    the lines within that many directions of it only (None or < 0: every direction)."""
    off, order, lg, p_below = win[:4]
    llr = np.asarray(llr, np.float64)
    if numba is not None and (compiled is None or bool(compiled)):
        weight, who = weight.astype(np.float64), who.astype(np.int64)
        A, B = A.astype(np.int64), B.astype(np.int64)

        def run(k):
            return _edge_window_numba(cat, weight, det, llr, who[k], A[k], B[k], off, order,
                                      lg, p_below, EDGE_MIN, EDGE_MISFIT, EDGE_CAP, EDGE_DET,
                                      -1 if span is None or span < 0 else int(span))

        parts = min(max(int(threads), 1), who.shape[0] // EDGE_PART)
        if parts <= 1:
            return run(slice(None))
        got = _in_parts(who.shape[0], parts, run)
        return np.concatenate([g[0] for g in got]), np.concatenate([g[1] for g in got])
    # (the numpy twin in chunks: each pixel's (directions, window) arrays)
    got = [_edge_window_numpy(cat, weight, det, llr, who[k:k + 512], A[k:k + 512],
                              B[k:k + 512], off, order, lg, p_below, span)
           for k in range(0, who.shape[0], 512)]
    if not got:
        return np.full(0, np.nan), np.full(0, -1)
    return np.concatenate([g[0] for g in got]), np.concatenate([g[1] for g in got])


def pair_say(la, lb, det, ia, ib, cap, det_w):
    """Each pixel's say for plane A against B (the windows' and edgelines.py's): an
    undetected pixel's log-likelihood ratio ``la - lb`` clipped to +-``cap`` (NaN, as
    -inf - -inf: none), a detected one +-``det_w`` for the plane it is on (``ia``,
    ``ib``: its label is A, B; neither: none)."""
    with np.errstate(invalid="ignore"):                           # (-inf - -inf: no say)
        e = np.clip(np.nan_to_num(la - lb, nan=0.0), -cap, cap)
    return np.where(det, np.where(ia, det_w, np.where(ib, -det_w, 0.0)), e)


def _edge_window_numpy(cat, weight, det, llr, who, A, B, off, order, lg, p_below,
                       span=None):
    """:func:`_edge_window`'s numpy twin on a chunk of pixels."""
    h, w = cat.shape
    post = np.full(who.shape[0], np.nan)
    kdir = np.full(who.shape[0], -1)
    r = who[:, 0, None] + off[:, 0]
    c = who[:, 1, None] + off[:, 1]
    ins = (r >= 0) & (r < h) & (c >= 0) & (c < w)
    rc, cc = np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)
    cw = np.where(ins, cat[rc, cc], -1)
    ia, ib = cw == A[:, None], cw == B[:, None]
    wt = np.where(ins, weight[rc, cc], 0.0)
    a, b = np.where(ia, wt, 0.0), np.where(ib, wt, 0.0)
    at, bt = a.sum(1), b.sum(1)
    # the misfit with A below a split: A's weight above it and B's below, at - (ca - cb)
    # (ca, cb: A's and B's below); with A above: bt + (ca - cb)
    d = np.cumsum((a - b)[:, order], -1)[..., :-1]                # (n, K, M - 1)
    fin = np.isfinite(lg)
    mis = np.minimum(at - np.where(fin, d, -np.inf).max((1, 2)),
                     bt + np.where(fin, d, np.inf).min((1, 2)))
    go = np.nonzero((at >= EDGE_MIN) & (bt >= EDGE_MIN) & (mis <= EDGE_MISFIT))[0]
    if not go.size:
        return post, kdir
    rc, cc, ia, ib = rc[go], cc[go], ia[go], ib[go]
    e = pair_say(llr[rc, cc, A[go, None]], llr[rc, cc, B[go, None]], det[rc, cc], ia, ib,
                 EDGE_CAP, EDGE_DET)
    e = np.where(ins[go], e, 0.0)
    ce = np.cumsum(e[:, order], -1)                               # (n, K, M)
    below = ce[..., :-1]
    s1 = below + lg                  # A below: the log-likelihood (up to a constant)
    s2 = (ce[..., -1:] - below) + lg  # A above
    pa = np.where(p_below, s1, s2)   # (n, K, M - 1): the splits that put p on A's side
    pb = np.where(p_below, s2, s1)
    # the best line's direction (the first of equals, as the numba twin)
    k = np.argmax(np.maximum(pa, pb).reshape(go.size, -1), -1) // (order.shape[1] - 1)
    kdir[go] = k
    if span is not None and span >= 0:      # the lines within span directions of it
        K = order.shape[0]
        gap = np.abs(np.arange(K)[None, :] - k[:, None])
        far = (np.minimum(gap, K - gap) > span)[..., None]        # (n, K, 1)
        pa = np.where(far, -np.inf, pa)
        pb = np.where(far, -np.inf, pb)
    pa, pb = pa.reshape(go.size, -1), pb.reshape(go.size, -1)
    top = np.maximum(pa.max(-1), pb.max(-1))[:, None]
    za = np.exp(pa - top).sum(-1)
    zb = np.exp(pb - top).sum(-1)
    post[go] = zb / (za + zb)
    return post, kdir


if numba is not None:
    @numba.njit(cache=True, nogil=True)
    def _edge_window_numba(cat, weight, det, llr, who, A, B, off, order, lg, p_below,
                           min_w, max_mis, cap, det_w, span):
        """:func:`_edge_window` a pixel at a time, without its temporaries (the same
        sums in the same order; ``span`` >= 0: the second sweep over the directions
        within it of the best line's only)."""
        h, w = cat.shape
        n, M, K, S = who.shape[0], off.shape[0], order.shape[0], order.shape[1] - 1
        post = np.full(n, np.nan)
        kdir = np.full(n, -1)
        wa = np.empty(M)
        wb = np.empty(M)
        e = np.empty(M)
        for i in range(n):
            at = 0.0
            bt = 0.0
            for q in range(M):
                r, c = who[i, 0] + off[q, 0], who[i, 1] + off[q, 1]
                wa[q] = 0.0
                wb[q] = 0.0
                e[q] = 0.0
                if r < 0 or r >= h or c < 0 or c >= w:
                    continue
                lab = cat[r, c]
                if lab == A[i]:
                    wa[q] = weight[r, c]
                elif lab == B[i]:
                    wb[q] = weight[r, c]
                at += wa[q]
                bt += wb[q]
                if det[r, c]:
                    e[q] = det_w if lab == A[i] else (-det_w if lab == B[i] else 0.0)
                else:
                    x = llr[r, c, A[i]] - llr[r, c, B[i]]
                    e[q] = 0.0 if x != x else min(max(x, -cap), cap)
            if at < min_w or bt < min_w:
                continue
            hi = -np.inf
            lo = np.inf
            for k in range(K):
                d = 0.0
                for s in range(S):
                    q = order[k, s]
                    d += wa[q] - wb[q]
                    if lg[k, s] > -np.inf:
                        hi = max(hi, d)
                        lo = min(lo, d)
            if min(at - hi, bt + lo) > max_mis:
                continue
            top = -np.inf
            for sweep in range(2):        # the largest log-likelihood, then the sums
                za = 0.0
                zb = 0.0
                for k in range(K):
                    if sweep == 1 and span >= 0 and \
                            min(abs(k - kdir[i]), K - abs(k - kdir[i])) > span:
                        continue              # (a direction too far from the best's)
                    tot = 0.0
                    for q in range(M):
                        tot += e[order[k, q]]
                    c1 = 0.0
                    for s in range(S):
                        c1 += e[order[k, s]]
                        if lg[k, s] == -np.inf:
                            continue
                        s1 = c1 + lg[k, s]            # A below the split
                        s2 = (tot - c1) + lg[k, s]    # A above
                        pa, pb = (s1, s2) if p_below[k, s] else (s2, s1)
                        if sweep == 0:
                            if max(pa, pb) > top:
                                top = max(pa, pb)
                                kdir[i] = k
                        else:
                            za += np.exp(pa - top)
                            zb += np.exp(pb - top)
            post[i] = zb / (za + zb)
        return post, kdir
