"""Edges as whole lines: the last step of the spatial estimator's labels (called by
:func:`stages.ranging.spatial._edges` after the windows of :func:`planecut.edge_side`).

The windows see 11 pixels of an edge. A straight boundary between two of the frame's
planes is as long as the object: the box's left edge in the benchmark's scene runs 22
pixels. Each pixel's own 2 signal photons (in 50 of background) hardly place it, the
edge's pixels all along do. This step finds the straight runs of the label image's
boundary between each pair of planes, weighs every line near each run (a tilt of +-2
degrees, an offset of +-1.5 pixels, integrated exactly: at each tilt the likelihood is a
step function of the offset between the band's pixels' sorted distances, so the
posterior is a cumulative sum over them) by the likelihood of the photons in a band
along the whole run, and moves the undetected pixels next to it that lie on the wrong side with a
posterior above ``LINE_P`` (0.5: the least expected squared error). Where two runs of
the same pair meet (a box's corner), the pixels around the point where their lines
cross follow both lines: on a plane's side of both where its corner is convex, of either
where it is concave; where the labels around the crossing fit that corner (two separate
objects' edges also cross near their runs' ends). The two lines are weighed together
there (:func:`_corner`): the pixels near both have their say once, on the side the
corner puts them. Every undetected pixel a line or a corner weighed is returned with its
posterior, for its sigma (``spatial._line_var``).

Two guards, from a first version that made the pixels off 11 -> 476 (docs/ranging.md
"Edges as whole lines"): a run is contiguous along its line (no gap over ``LINE_GAP``
pixels, so a line through scattered boundary points of two planes that meet nowhere is
no run), and its band's labels fit its line (misfit at most ``LINE_MISFIT``, over the
run's own extent: past its ends, at a corner, the band holds the other edge's pixels).
And only the
pixels within ``LINE_NEAR`` of the line, inside the run less a pixel at each end, move:
one wrong label at a run's end lengthens it, and the band would carry that error along.
The corners move the pixels past the runs' ends.

A detected pixel is never moved as the others are. Where it lies within ``LINE_NEAR``
of a run's line, inside the run, its detection is doubted when its own photons' whole
log-likelihood ratio between the two planes (not clipped), added to the line's log-odds
of its side without its own say, puts it on the other plane (posterior above
``LINE_P_DET``): a detection at the other plane's time that background passes at the
frame's p_fa, among the ~300 pixels of a frame beside an edge. The caller withdraws it
(the pixel takes the line's plane, its sigma keeps the chance it is where it was
detected). The misfit counts only the labels a detection or the pixel's own photons back
(photons that favour a plane over none): in the sky beside an object the relabelling
gives every pixel one of its neighbours' planes, and those labels say nothing.

numpy (and scipy.special's logsumexp and expit). The caller runs it twice
(``spatial.LINE_PASSES``), the second pass on the labels the first corrected; each pass
costs 20-25 ms a frame of 64 x 64 at (2, 50) (a few dozen runs, a few corners;
docs/ranging.md "The lines twice, their offsets integrated")."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.special import expit, logsumexp

from stages.ranging import planecut

LINE_DIRS = 72        # the directions voted over (2.5 degrees apart)
LINE_MIN = 8          # boundary points a run needs
LINE_INLIER = 0.75    # pixels: a boundary point this near the line is on it
LINE_GAP = 2.0        # pixels: a gap along the line this long ends a run
LINE_BAND = 3.0       # pixels either side of the line whose photons weigh it
LINE_TILT = np.deg2rad(2.0)   # the tilts tried about the run's fit: up to this
LINE_TILT_STEP = np.deg2rad(0.5)   # in steps of at most this, and of at most
LINE_TILT_END = 0.05  # pixels: the run's ends' move from one tilt to the next
LINE_SHIFT = 1.5      # and offsets (pixels) up to this, every one: the evidence is a step
#                       function of the offset between the band's distances from the line,
#                       and the posterior its exact integral (a grid of offsets 0.05 px apart
#                       put a long edge's posterior on one grid line, a pixel's side the
#                       truth's is not; 0.01 apart cost 5x the step)
LINE_MISFIT = 0.05    # the band's labels on the wrong side of the best line at most
LINE_NEAR = 1.0       # pixels: a pixel this near the line may move
LINE_P = 0.5          # the posterior of the other side from which a pixel moves (the
#                       Bayes decision for the squared error)
LINE_DET = 6.0        # nats: a detected pixel's say for its plane (the windows': 12)
LINE_CORNER = 6.0     # pixels: two runs whose lines cross this near both their ends meet
LINE_ZONE = 3         # the corner's pixels: within this many of the crossing (rows, cols)
LINE_TURN = np.deg2rad(20.0)   # the least angle between a corner's two lines
LINE_MISFIT_CORNER = 0.15  # the corner's zone: its labels off the two best lines at most
LINE_P_DET = 0.5      # a detected pixel: the other side's posterior (the line without its
#                       say, with its own photons' whole likelihood) from which it is doubted


def boundary_points(cat: np.ndarray) -> dict:
    """The midpoints (row, col) between 4-neighbours on two planes, by the pair
    (A, B), A < B (-1: no plane, not counted)."""
    pts, keys = [], []
    for axis in (0, 1):
        a = cat[:-1, :] if axis == 0 else cat[:, :-1]
        b = cat[1:, :] if axis == 0 else cat[:, 1:]
        r, c = np.nonzero((a != b) & (a >= 0) & (b >= 0))
        la, lb = a[r, c], b[r, c]
        pts.append(np.stack([r + 0.5 * (axis == 0), c + 0.5 * (axis == 1)], -1))
        keys.append(np.stack([np.minimum(la, lb), np.maximum(la, lb)], -1))
    pts, keys = np.concatenate(pts), np.concatenate(keys)
    out = {}
    if not keys.size:
        return out
    u, inv = np.unique(keys, axis=0, return_inverse=True)
    for g, (A, B) in enumerate(u):
        out[(int(A), int(B))] = pts[inv.ravel() == g]
    return out


def _tls(P: np.ndarray):
    """The total-least-squares line through points: (normal, tangent, centre)."""
    m = P.mean(0)
    _, _, vt = np.linalg.svd(P - m)
    return vt[1], vt[0], m


def runs(pts: np.ndarray) -> list:
    """The straight contiguous runs through boundary points (n, 2): a Hough vote
    (``LINE_DIRS`` directions, half-pixel bins, two neighbouring bins together: a
    staircase's points spread over a pixel), the best line's points refitted by total
    least squares, split where a gap along it exceeds ``LINE_GAP``; each part of
    ``LINE_MIN`` points or more is a run, and the line's points leave the vote. Returns
    (normal, tangent, centre, t0, t1) a run: its extent along the tangent."""
    th = np.arange(LINE_DIRS) * np.pi / LINE_DIRS
    nrm = np.stack([np.cos(th), np.sin(th)], -1)
    out = []
    pool = np.ones(len(pts), bool)
    while pool.sum() >= LINE_MIN:
        idx = np.nonzero(pool)[0]
        proj = pts[idx] @ nrm.T                                   # (n, K)
        b = np.floor(proj / 0.5).astype(np.int64)
        b0 = int(b.min())
        b -= b0
        nb = int(b.max()) + 2
        votes = np.zeros((LINE_DIRS, nb), np.int64)
        np.add.at(votes, (np.broadcast_to(np.arange(LINE_DIRS), b.shape), b), 1)
        pair = votes[:, :-1] + votes[:, 1:]
        k, j = np.unravel_index(np.argmax(pair), pair.shape)
        if pair[k, j] < LINE_MIN:
            break
        near = np.abs(proj[:, k] - (b0 + j + 1) * 0.5) <= LINE_INLIER   # bins j, j + 1
        inl = idx[near]
        n, tan, m = _tls(pts[inl])
        inl = inl[np.abs((pts[inl] - m) @ n) <= LINE_INLIER]
        pool[idx[near]] = False
        pool[inl] = False
        t = pts[inl] @ tan
        o = np.argsort(t)
        inl, t = inl[o], t[o]
        cuts = np.nonzero(np.diff(t) > LINE_GAP)[0] + 1
        for part in np.split(inl, cuts):
            if part.size >= LINE_MIN:
                n2, tan2, m2 = _tls(pts[part])
                if tan2 @ tan < 0:
                    tan2 = -tan2
                t2 = pts[part] @ tan2             # (its extent along its own tangent)
                out.append((n2, tan2, m2, float(t2.min()), float(t2.max())))
    return out


def tilts(length: float) -> np.ndarray:
    """The tilts tried about a run's fit (radians), +-``LINE_TILT``: steps of at most
    ``LINE_TILT_STEP`` that move the ends of a run ``length`` pixels long by at most
    ``LINE_TILT_END`` (on a run of 60 pixels, steps of 0.5 degrees move its ends by a
    quarter of a pixel: the best tilt misses a pixel beside the line by that much, and
    the run's whole photons hold that line with tens of nats)."""
    step = min(LINE_TILT_STEP, 2.0 * LINE_TILT_END / max(length, 1.0))
    k = int(np.ceil(LINE_TILT / step - 1e-9))
    return np.linspace(-LINE_TILT, LINE_TILT, 2 * k + 1)


class _Segments(NamedTuple):
    """A run's lines by tilt and by the segment of offsets between two of its pixels'
    distances: ``rank`` (m, P) each pixel's place among the distances at each tilt,
    ``lw`` (P, m + 1) each segment's log weight (its evidence and its length; -inf for
    none), ``edges`` (m + 2, P) the segments' ends. Under the lines of segment j at tilt
    p, pixel i is on the + side where its rank is j or more."""

    rank: np.ndarray
    lw: np.ndarray
    edges: np.ndarray


def _segments(xy, say, centre, normals, a_pos) -> _Segments:
    """The lines (``normals`` (P, 2) through ``centre`` shifted by every offset within
    +-``LINE_SHIFT``) weighed by the say of the pixels ``xy`` (m, 2) on A's side: at each
    tilt the evidence changes only where the offset passes a pixel's distance, so the
    offsets between two sorted distances are one segment, weighed by its length."""
    d = (xy - centre) @ normals.T                                         # (m, P)
    m, P = d.shape
    order = np.argsort(d, axis=0, kind="stable")
    ds = np.take_along_axis(d, order, 0)
    edges = np.concatenate([np.full((1, P), -LINE_SHIFT),
                            np.clip(ds, -LINE_SHIFT, LINE_SHIFT), np.full((1, P), LINE_SHIFT)])
    pre = np.concatenate([np.zeros((1, P)), np.cumsum(say[order], 0)])   # rank < j's say
    ll = pre[-1] - pre if a_pos else pre      # A's side: the + one (rank >= j), or not
    with np.errstate(divide="ignore"):
        lw = (ll + np.log(np.diff(edges, axis=0))).T
    rank = np.empty_like(order)
    np.put_along_axis(rank, order, np.broadcast_to(np.arange(m)[:, None], (m, P)), 0)
    return _Segments(rank, lw, edges)


def _side_posterior(seg: _Segments, a_pos: bool) -> np.ndarray:
    """Each pixel's posterior of A's side: on the + side under the segments up to its
    rank."""
    post = np.exp(seg.lw - seg.lw.max())
    post /= post.sum()
    cum = np.cumsum(post, 1)
    below = cum[np.arange(post.shape[0]), seg.rank].sum(1)
    return below if a_pos else 1.0 - below


def _best(seg: _Segments, normals, centre):
    """The best line: its (tilt, segment), the segment of most weight, and its (normal,
    offset) at the segment's middle."""
    jp, js = np.unravel_index(np.argmax(seg.lw), seg.lw.shape)
    n = normals[jp]
    return jp, js, (n, float(n @ centre + 0.5 * (seg.edges[js, jp] + seg.edges[js + 1, jp])))


class _Line:
    """A run's line: the tilts' normals about ``centre`` and the best line (``n_map``,
    ``rho_map``); ``band``: its band's pixels and their say (for its corners)."""

    def __init__(self, A, B, tan, centre, t0, t1, a_pos, normals, best, band=None):
        self.A, self.B, self.tan, self.centre = A, B, tan, centre
        self.t0, self.t1, self.a_pos = t0, t1, a_pos
        self.normals = normals
        self.q, self.say = band if band is not None else (None, None)
        self.n_map, self.rho_map = best

    def map_on_a(self, xy: np.ndarray) -> bool:
        s = bool(self.n_map @ xy - self.rho_map > 0)
        return s if self.a_pos else not s


def _reach(centre, tan, t0, t1, h, w):
    """The extent along a run's line (``tan``) whose pixels may move: the run's less a
    pixel at each end (a wrong label there lengthens it), or on to the image's border
    where the line leaves the image within ``LINE_CORNER`` of the run's end (no corner
    fits between; the first row of a floor at the left border, seed 12 at (2, 50)). The
    band whose photons weigh the line reaches as far."""
    c0 = centre @ tan
    with np.errstate(divide="ignore"):        # (along an axis: +-inf, never left that way)
        ends = np.stack([(np.array([-0.5, -0.5]) - centre) / tan,
                         (np.array([h - 0.5, w - 0.5]) - centre) / tan])
    lo_in = c0 + np.min(ends, 0).max()       # where the line enters and leaves the image
    hi_in = c0 + np.max(ends, 0).min()
    lo = lo_in if lo_in >= t0 - LINE_CORNER else t0 + 1.0
    hi = hi_in if hi_in <= t1 + LINE_CORNER else t1 - 1.0
    return lo, hi


def _evidence(q, A, B, cat, dets, lp, cap, det_w):
    """Each pixel's (flat indices ``q``) say for A against B, as the windows weigh it:
    an undetected one's log-likelihood ratio clipped to +-``cap``, a detected one
    +-``det_w`` for the plane it is on."""
    w = cat.shape[1]
    rq, cq = q // w, q % w
    lab = cat.ravel()[q]
    return planecut.pair_say(lp[rq, cq, A], lp[rq, cq, B], dets.ravel()[q], lab == A,
                             lab == B, cap, det_w)


def _moves(q, p_a, lab, A, B):
    """(pixels, planes) of ``q`` whose label is the side the posterior puts below
    1 - ``LINE_P``."""
    to_b = (lab == A) & (1.0 - p_a > LINE_P)
    to_a = (lab == B) & (p_a > LINE_P)
    return (np.concatenate([q[to_b], q[to_a]]),
            np.concatenate([np.full(to_b.sum(), B), np.full(to_a.sum(), A)]))


class LineMoves(NamedTuple):
    """What :func:`line_moves` found (flat pixel indices, plane indices): the pixels to
    move and their planes (``q``, ``pl``); the detections doubted, the planes the lines
    put them on and the posterior that each lies where it was detected (``doubt_q``,
    ``doubt_pl``, ``p_was``); and every undetected pixel a line or a corner weighed
    for a move, with the pair of planes and its posterior of A's side (``seen_q``,
    ``seen_a``, ``seen_b``, ``seen_p_a``; a pixel once for each line or corner that
    weighed it)."""

    q: np.ndarray
    pl: np.ndarray
    doubt_q: np.ndarray
    doubt_pl: np.ndarray
    p_was: np.ndarray
    seen_q: np.ndarray
    seen_a: np.ndarray
    seen_b: np.ndarray
    seen_p_a: np.ndarray


class _Seen(NamedTuple):
    """The undetected pixels one line or corner weighed (flat indices), its pair of
    planes and each pixel's posterior of A's side; whether a corner weighed them."""

    q: np.ndarray
    A: int
    B: int
    p_a: np.ndarray
    corner: bool


def line_moves(cat, weight, dets, lp, cap, det_w) -> LineMoves:
    """The pixels to move, the detections doubted and the posteriors the moves were
    decided on (:class:`LineMoves`): see the module's docstring. ``cat`` (h, w) each
    pixel's plane (-1: none), ``weight`` the labels' weights (as the windows'), ``dets``
    (h, w) detected pixels (never moved; their say is +-``det_w``), ``lp`` (h, w, L)
    each plane's log-likelihood a pixel (an undetected pixel's say between two: clipped
    to +-``cap``). A pixel two lines or corners would send to different planes stays."""
    h, w = cat.shape
    rr, cc = np.mgrid[0:h, 0:w]
    X = np.stack([rr.ravel(), cc.ravel()], -1).astype(np.float64)
    catf, wf, detf = cat.ravel(), weight.ravel(), dets.ravel()
    lines, doubt, seen = [], [], []
    for (A, B), pts in boundary_points(cat).items():
        if len(pts) < LINE_MIN:
            continue
        ab = (catf == A) | (catf == B)
        for n, tan, centre, t0, t1 in runs(pts):
            d, t = (X - centre) @ n, X @ tan
            lo, hi = _reach(centre, tan, t0, t1, h, w)
            q = np.nonzero(ab & (np.abs(d) <= LINE_BAND) & (t >= min(lo, t0 - 0.5))
                           & (t <= max(hi, t1 + 0.5)))[0]
            if q.size < 2 * LINE_MIN:
                continue
            la = catf[q]
            wa, wb = wf[q] * (la == A), wf[q] * (la == B)
            pos = d[q] > 0
            a_pos = bool((wa * ~pos).sum() + (wb * pos).sum()
                         < (wa * pos).sum() + (wb * ~pos).sum())    # A's side: the + one
            phi = np.arctan2(n[1], n[0]) + tilts(t1 - t0)
            normals = np.stack([np.cos(phi), np.sin(phi)], -1)
            say = _evidence(q, A, B, cat, dets, lp, cap, det_w)
            seg = _segments(X[q], say, centre, normals, a_pos)
            jp, jo, best_line = _best(seg, normals, centre)
            line = _Line(A, B, tan, centre, t0, t1, a_pos, normals, best_line, (q, say))
            best = (seg.rank[:, jp] >= jo) == a_pos
            # the misfit of the labels a detection or the pixel's own photons back (one
            # whose photons favour no surface over either plane, as in the sky beside
            # a box, holds a label its neighbours gave it)
            rq, cq = q // w, q % w
            back = detf[q] | (np.fmax(lp[rq, cq, A], lp[rq, cq, B]) > 0)
            back &= (t[q] >= t0) & (t[q] <= t1)   # (the run's own: past its ends, at a
            #   corner, the band holds the other edge's pixels: a box's 16-pixel top edge,
            #   noise-free, misfit its exact line by 6 %)
            wa_, wb_ = wa * back, wb * back
            tot = wa_.sum() + wb_.sum()
            if tot <= 0 or (wa_ * ~best).sum() + (wb_ * best).sum() > LINE_MISFIT * tot:
                continue
            lines.append(line)
            p_a = _side_posterior(seg, a_pos)
            inside = (np.abs(d[q]) <= LINE_NEAR) & (t[q] >= lo) & (t[q] <= hi)
            ok = ~detf[q] & inside
            seen.append(_Seen(q[ok], A, B, p_a[ok], False))
            # (a detection within LINE_NEAR of the line, as the moves, but only inside
            # the run itself less a pixel at each end: the line carried on to the border
            # is no evidence against a detection; beyond LINE_NEAR, at an acute corner,
            # the band holds the other edge's pixels)
            dq = np.nonzero(detf[q] & (np.abs(d[q]) <= LINE_NEAR) & (t[q] >= t0 + 1.0)
                            & (t[q] <= t1 - 1.0))[0]
            if dq.size:
                got = _doubt(q[dq], seg, dq, a_pos, say[dq], la[dq], lp, w, A, B)
                doubt.append(got)
    # corners: two runs of the same pair whose lines cross near both their ends
    for i, l1 in enumerate(lines):
        for l2 in lines[i + 1:]:
            if (l1.A, l1.B) != (l2.A, l2.B) or abs(l1.n_map @ l2.n_map) > np.cos(LINE_TURN):
                continue
            at = np.linalg.solve(np.stack([l1.n_map, l2.n_map]), [l1.rho_map, l2.rho_map])
            if not all(ln.t0 - LINE_CORNER <= at @ ln.tan <= ln.t1 + LINE_CORNER
                       and not ln.t0 + LINE_CORNER < at @ ln.tan < ln.t1 - LINE_CORNER
                       for ln in (l1, l2)):
                continue
            # A's corner is convex where each run lies on A's side of the other's line
            convex = l2.map_on_a(l1.centre)
            if convex != l1.map_on_a(l2.centre):
                continue
            ir, ic = np.round(at).astype(np.int64)
            r0, r1 = max(ir - LINE_ZONE, 0), min(ir + LINE_ZONE + 1, h)
            c0, c1 = max(ic - LINE_ZONE, 0), min(ic + LINE_ZONE + 1, w)
            if r0 >= r1 or c0 >= c1:
                continue
            zr, zc = np.mgrid[r0:r1, c0:c1]
            q = (zr * w + zc).ravel()
            q = q[(catf[q] == l1.A) | (catf[q] == l1.B)]
            # the zone's labels must fit the corner (two runs of separate objects also
            # cross near their ends: two boxes, one's side and the other's top)
            a1 = (X[q] @ l1.n_map - l1.rho_map > 0) == l1.a_pos
            a2 = (X[q] @ l2.n_map - l2.rho_map > 0) == l2.a_pos
            fit = (a1 & a2) if convex else (a1 | a2)
            wq = wf[q]
            off = (wq * (fit != (catf[q] == l1.A))).sum()
            if not q.size or off > LINE_MISFIT_CORNER * wq.sum():
                continue
            J = np.union1d(q, np.intersect1d(l1.q, l2.q))
            p_a = _corner(l1, l2, q, J, convex, X,
                          _evidence(J, l1.A, l1.B, cat, dets, lp, cap, det_w))
            und = ~detf[q]
            if und.any():
                seen.append(_Seen(q[und], l1.A, l1.B, p_a[und], True))
    # a pixel a corner weighed is the corner's for that pair of planes: the pair's
    # lines' records there (each line alone, as if it went on past the corner) neither
    # move it nor give its sigma (another pair's line still does: a floor's edge
    # through a board's corner)
    for i, x in enumerate(seen):
        zones = [y.q for y in seen if y.corner and (y.A, y.B) == (x.A, x.B)]
        if zones and not x.corner:
            keep = ~np.isin(x.q, np.concatenate(zones))
            seen[i] = x._replace(q=x.q[keep], p_a=x.p_a[keep])
    none = np.zeros(0, np.int64)
    moves, sq, sa, sb, sp = (none, none), none, none, none, np.zeros(0)
    if seen:
        got = [_moves(x.q, x.p_a, catf[x.q], x.A, x.B) for x in seen]
        moves = one_plane(np.concatenate([m[0] for m in got]),
                          np.concatenate([m[1] for m in got]))
        sq = np.concatenate([x.q for x in seen])
        sa = np.concatenate([np.full(x.q.size, x.A) for x in seen])
        sb = np.concatenate([np.full(x.q.size, x.B) for x in seen])
        sp = np.concatenate([x.p_a for x in seen])
    if not doubt:
        return LineMoves(*moves, none, none, np.zeros(0), sq, sa, sb, sp)
    dq, dpl, dp = (np.concatenate(x) for x in zip(*doubt, strict=True))
    uq, upl = one_plane(dq, dpl)
    # (a pixel two lines doubt towards one plane: the larger chance it is where it was)
    keep = np.isin(dq, uq)
    p_was = np.zeros(uq.size)
    np.maximum.at(p_was, np.searchsorted(uq, dq[keep]), dp[keep])
    return LineMoves(*moves, uq, upl, p_was, sq, sa, sb, sp)


def _patterns(line, J, X):
    """The distinct sides (True: A's) of the pixels ``J`` (sorted flat indices) under
    the line's every (tilt, offset), each with the log of the posterior weight of the
    lines that give it, from the line's log-evidence less the say of the pixels of
    ``J`` in its band: (patterns (k, j), log weights (k,)). The offsets' segments are
    those between the distances of the band's pixels and of ``J``'s."""
    inb = np.isin(line.q, J)
    extra = np.setdiff1d(J, line.q)
    pts = np.concatenate([line.q, extra])
    say = np.concatenate([np.where(inb, 0.0, line.say), np.zeros(extra.size)])
    seg = _segments(X[pts], say, line.centre, line.normals, line.a_pos)
    rank = seg.rank[_positions(pts, J)]                                   # (j, P)
    ok = np.isfinite(seg.lw)                                               # (P, S)
    p_idx, s_idx = np.nonzero(ok)
    up = rank[:, p_idx] >= s_idx                                           # (j, K)
    flat = (up if line.a_pos else ~up).T                                   # (K, j)
    lw = seg.lw[p_idx, s_idx]
    # the sides as 64-bit words (exact), sorted; a new pattern where a word changes
    packed = np.packbits(flat, axis=1)
    pad = -packed.shape[1] % 8
    words = np.ascontiguousarray(np.pad(packed, ((0, 0), (0, pad)))).view(np.uint64)
    order = np.lexsort(words.T[::-1])
    new = np.ones(len(order), bool)
    new[1:] = (np.diff(words[order], axis=0) != 0).any(1)
    starts = np.nonzero(new)[0]
    return flat[order[starts]], np.logaddexp.reduceat(lw[order], starts)


def _positions(pts, J):
    """Where each of ``J`` is in ``pts`` (every one of ``J`` is there once)."""
    o = np.argsort(pts, kind="stable")
    return o[np.searchsorted(pts, J, sorter=o)]


def _corner(l1, l2, Z, J, convex, X, say):
    """The posterior of A's side for each pixel of a corner's zone ``Z`` (sorted flat
    indices) under its two lines together. The pixels near both, ``J`` (sorted: the
    zone and the pixels in both bands; ``say`` theirs, in its order), are on A's side
    where the corner puts them: on A's side of both lines where A's corner is convex,
    of either where it is concave. Each line's posterior without their say, times their
    say once under the corner: the product of the two lines' posteriors counts a
    pixel in both bands twice, and treats as apart two lines that such pixels tie."""
    p1, w1 = _patterns(l1, J, X)
    p2, w2 = _patterns(l2, J, X)
    p1, p2 = p1.astype(np.float64), p2.astype(np.float64)                # (k1, j), (k2, j)
    both = (p1 * say) @ p2.T                     # the say of the pixels on A's side of both
    L = w1[:, None] + w2[None, :] + (both if convex
                                     else (p1 @ say)[:, None] + (p2 @ say)[None, :] - both)
    post = np.exp(L - L.max())
    post /= post.sum()
    on_both = ((post @ p2) * p1).sum(0)          # each pixel's posterior of both, of either
    p_a = on_both if convex else post.sum(1) @ p1 + post.sum(0) @ p2 - on_both
    return np.clip(p_a[np.searchsorted(J, Z)], 0.0, 1.0)


def _doubt(q, seg, k, a_pos, say, lab, lp, w, A, B):
    """The detected pixels ``q`` (the band's pixels ``k`` of the run's lines ``seg``,
    their say in it ``say``, labels ``lab``) whose own photons' whole log-likelihood
    ratio (``lp``, not clipped), added to the line's log-odds of their side without
    their say, puts them on the other plane with a posterior above ``LINE_P_DET``:
    (pixels, the other planes, the posterior that each lies where it was detected)."""
    with np.errstate(invalid="ignore"):                       # (-inf with -inf: -inf)
        upto = np.logaddexp.accumulate(seg.lw, axis=1)                    # segments <= j
        past = np.logaddexp.accumulate(seg.lw[:, ::-1], axis=1)[:, ::-1]  # segments >= j
    P = np.arange(seg.lw.shape[0])
    r = seg.rank[k]                                                       # (m, P)
    past = np.concatenate([past, np.full((len(P), 1), -np.inf)], 1)
    plus, minus = logsumexp(upto[P, r], axis=1), logsumexp(past[P, r + 1], axis=1)
    on, off = (plus, minus) if a_pos else (minus, plus)
    with np.errstate(invalid="ignore"):                       # (no line either side: NaN)
        line = on - off - say                                 # without the pixel
    rq, cq = q // w, q % w
    with np.errstate(invalid="ignore"):
        own = lp[rq, cq, A] - lp[rq, cq, B]
    # (a plane whose pulse lies outside the window at the pixel, -inf: no doubt)
    z = np.where(np.isfinite(own) & ~np.isnan(line), own + line, 0.0)
    cut = np.log(LINE_P_DET / (1 - LINE_P_DET))
    to_b, to_a = (lab == A) & (z < -cut), (lab == B) & (z > cut)
    p_a = expit(z)
    return (np.concatenate([q[to_b], q[to_a]]),
            np.concatenate([np.full(to_b.sum(), B), np.full(to_a.sum(), A)]),
            np.concatenate([p_a[to_b], 1.0 - p_a[to_a]]))


def one_plane(q: np.ndarray, pl: np.ndarray):
    """The moves (pixels ``q``, planes ``pl``) with each pixel once: a pixel sent to
    one plane (by one line or several) goes there, one sent to two stays."""
    q, pl = np.asarray(q, np.int64), np.asarray(pl, np.int64)
    order = np.lexsort((pl, q))
    q, pl = q[order], pl[order]
    uq, first, cnt = np.unique(q, return_index=True, return_counts=True)
    one = pl[first] == pl[first + cnt - 1]
    return uq[one], pl[first][one]
