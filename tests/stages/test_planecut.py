"""The spatial estimator's graph-cut start (stages/ranging/planecut.py): the expansion
against brute force, the cut's cost against the Euclidean length, the planes found from
noisy returns, and the likelihood against a sum written out bin by bin."""

from itertools import product

import numpy as np
import pytest
from scipy.stats import norm

from stages.ranging import planecut


def _energy(D, lab, lam):
    h, w, _ = D.shape
    e = np.take_along_axis(D, lab[..., None], -1).sum()
    for i, j, wt in planecut._pairs(h, w):
        sp, sq = planecut._sl(i, j, h, w)
        e += lam * wt * (lab[sp] != lab[sq]).sum()
    return e


def _brute(D, lam):
    h, w, L = D.shape
    return min(_energy(D, np.array(x).reshape(h, w), lam)
               for x in product(range(L), repeat=h * w))


@pytest.mark.parametrize("seed", range(6))
def test_two_labels_are_the_exact_minimum(seed):
    """With two labels one expansion is the global minimum (a single max-flow)."""
    rng = np.random.default_rng(seed)
    D = rng.normal(0, 1.5, (3, 4, 2))
    lab = planecut.expand(D, lam=2.0)
    assert _energy(D, lab, 2.0) == pytest.approx(_brute(D, 2.0), abs=1e-9)


@pytest.mark.parametrize("seed", range(4))
def test_three_labels_within_the_expansion_bound(seed):
    """Alpha-expansion's bound for Potts: within twice the global minimum of the pair
    term, never below the minimum, never above where it started (each label's argmin)."""
    rng = np.random.default_rng(seed)
    D = rng.uniform(0, 3, (2, 4, 3))
    lab = planecut.expand(D, lam=1.5)
    e, best = _energy(D, lab, 1.5), _brute(D, 1.5)
    assert best - 1e-9 <= e <= 2 * best + 1e-9
    assert e <= _energy(D, np.argmin(D, -1), 1.5) + 1e-9


@pytest.mark.parametrize("angle", [0, 10, 30, 45, 60, 80])
def test_a_cut_costs_its_length_at_any_angle(angle):
    """A straight boundary's cut cost over its length is 1 within 7 % at any angle (the
    16-neighbourhood's weights; a 4-neighbourhood's is off by up to 41 % at 45 deg)."""
    n = 161
    r, c = np.mgrid[0:n, 0:n] - n // 2
    a = np.deg2rad(angle)
    lab = (r * np.cos(a) - c * np.sin(a) > 0.3).astype(int)
    inner = (slice(20, n - 20), slice(20, n - 20))
    cost = 0.0
    for i, j, wt in planecut._pairs(n, n):
        sp, sq = planecut._sl(i, j, n, n)
        cut = np.zeros((n, n), bool)
        cut[sp] = lab[sp] != lab[sq]
        cost += wt * cut[inner].sum()
    # the boundary's length inside the inner square (edges counted at their first node)
    length = (n - 40) / max(abs(np.cos(a)), abs(np.sin(a)))
    assert cost / length == pytest.approx(1.0, rel=0.07)


def test_a_line_of_pixels_cuts_at_one():
    """A single row or column: one neighbour each way, a boundary costing 1; one pixel:
    no pair."""
    assert planecut._pairs(1, 9) == [(0, 1, 1.0)]
    assert planecut._pairs(9, 1) == [(1, 0, 1.0)]
    assert planecut._pairs(1, 1) == []
    D = np.array([[[0.0, 3.0]] * 4 + [[3.0, 0.0]] * 4])
    assert planecut.expand(D, lam=2.0).tolist() == [[0, 0, 0, 0, 1, 1, 1, 1]]


def test_planes_are_found_from_noisy_returns():
    """Two planes (returns scattered 0.8 bin about them, slopes 0.1 bin a pixel) and 3 %
    false returns: both planes come back within 0.4 bin at every pixel of the image
    (measured 0.09 and 0.26), in the order of their support, and the false returns make
    none."""
    rng = np.random.default_rng(3)
    h, w = 40, 40
    r, c = np.mgrid[0:h, 0:w].astype(float)
    A, B = (300.0, 0.4, 1.2), (520.0, -2.0, 0.1)
    left = c < 24
    t = np.where(left, A[0] + A[1] * r + A[2] * c, B[0] + B[1] * r + B[2] * c)
    t = t + rng.normal(0, 0.8, t.shape)
    det = rng.random((h, w)) < 0.7
    junk = rng.random((h, w)) < 0.03
    t = np.where(junk, rng.uniform(0, 1000, t.shape), t)
    slope = np.stack([np.where(left, A[1], B[1]), np.where(left, A[2], B[2])], -1)
    slope = slope + rng.normal(0, 0.1, slope.shape)
    tb, sl = t[..., None], slope[:, :, None, :]
    got = planecut.planes(tb, sl, det[..., None], np.full((h, w, 1), 2.0),
                          np.full((h, w, 1), 1e-11), tol=7.0)
    assert len(got) == 2
    for (a, s, sg), want in zip(got, (A, B), strict=True):
        fit = a[0] + a[1] * r + a[2] * c
        assert np.max(np.abs(fit - (want[0] + want[1] * r + want[2] * c))) < 0.4
        assert s == 2.0 and sg == 1e-11


def test_planes_of_nothing():
    """No detection, or fewer than a plane needs: no plane."""
    tb = np.full((5, 5, 1), 100.0)
    sl = np.zeros((5, 5, 1, 2))
    one = np.ones((5, 5, 1))
    assert planecut.planes(tb, sl, np.zeros((5, 5, 1), bool), one, one, 7.0) == []
    few = np.zeros((5, 5, 1), bool)
    few[0, :planecut.PLANE_MIN - 1] = True
    assert planecut.planes(tb, sl, few, one, one, 7.0) == []


def test_gauss_llr_is_the_sum_over_bins():
    """The likelihood ratio against the sum over every bin written out, with a
    background profile (the pulse's tails beyond +-4 sigma, 6e-5 of it, left out); NaN
    and a pulse mostly outside the window give -inf; zero counts give -S times the
    pulse's share inside."""
    rng = np.random.default_rng(5)
    h, w, n, sb = 3, 4, 120, 2.3
    counts = rng.poisson(0.4, (h, w, n)).astype(float)
    P0 = np.concatenate([np.zeros((h, w, 1)), np.cumsum(counts, -1)], -1)
    beta = rng.uniform(0.2, 0.6, (h, w))
    shape = np.linspace(0.5, 1.5, n)
    T = rng.uniform(10, 110, (h, w, 2))
    T[0, 0, 1] = np.nan
    T[1, 1, 0] = -30.0
    S = np.array([1.5, 3.0])
    got = planecut.gauss_llr(P0, beta, T, S, sb, shape)
    for y, x, k in product(range(h), range(w), range(2)):
        t = T[y, x, k]
        if not np.isfinite(t) or t < 0:
            assert got[y, x, k] == -np.inf
            continue
        j = np.arange(n)
        p = norm.cdf((j + 1 - t) / sb) - norm.cdf((j - t) / sb)
        want = np.sum(counts[y, x] * np.log1p(S[k] * p / (beta[y, x] * shape))) \
            - S[k] * p.sum()
        assert got[y, x, k] == pytest.approx(want, abs=1e-3)
    zero = planecut.gauss_llr(np.zeros((1, 1, n + 1)), np.ones((1, 1)),
                              np.array([[[60.0]]]), np.array([2.0]), sb)
    assert zero[0, 0, 0] == pytest.approx(-2.0, rel=1e-4)


def test_start_labels_a_frame_without_detections_none():
    """No detected pixel: no plane, no start (the sweeps start as they did)."""
    h, w, n = 6, 6, 64
    tb = np.full((h, w, 2), np.nan)
    got = planecut.start(tb, np.zeros((h, w, 2, 2)), np.zeros((h, w, 2), bool),
                         np.zeros((h, w, 2)), np.full((h, w, 2), np.inf),
                         np.zeros((h, w, n + 1)), np.full((h, w), 0.1), 2.3)
    assert got is None


def _square(n, half, angle_deg):
    """Labels 1 inside a square of half-side ``half`` about the image's centre, turned by
    ``angle_deg``, 0 outside; and each pixel's coordinates (u, v) along its sides."""
    r, c = np.mgrid[0:n, 0:n] - (n - 1) / 2.0
    a = np.deg2rad(angle_deg)
    u = r * np.cos(a) + c * np.sin(a)
    v = -r * np.sin(a) + c * np.cos(a)
    return ((np.abs(u) < half) & (np.abs(v) < half)).astype(np.int64), u, v


def _corner_case(lab, r, c):
    """The square's labels with every pixel detected but (r, c), and no photons' say."""
    det = np.ones(lab.shape, bool)
    det[r, c] = False
    return (lab, np.ones(lab.shape), det, np.zeros(lab.shape + (2,)), np.array([[r, c]]))


@pytest.mark.parametrize("compiled", [None, False])
@pytest.mark.parametrize("angle", [0, 10, 17, 30, 45, 60, 73])
def test_a_corner_pixel_goes_with_its_edges_at_any_angle(angle, compiled):
    """The pixel nearest each corner of a square, labelled as what surrounds it, is put
    back on the square (posterior > EDGE_P) by the windows beside it, along its two
    edges: the window centred on it is no straight boundary. The pixel is the one
    nearest the corner at least half a pixel inside both edges."""
    lab, u, v = _square(41, 11.3, angle)
    inside = 11.3 - np.maximum(np.abs(u), np.abs(v)) >= 0.5
    for su, sv in product((-1, 1), repeat=2):
        score = np.where(inside, su * u + sv * v, -np.inf)
        r, c = np.unravel_index(np.argmax(score), lab.shape)
        cat = lab.copy()
        cat[r, c] = 0
        post = planecut.edge_side(*_corner_case(cat, r, c), np.array([0]), np.array([1]),
                                  compiled)
        assert post[0] > planecut.EDGE_P, (angle, r, c, post)


@pytest.mark.parametrize("compiled", [None, False])
@pytest.mark.parametrize("angle", [0, 10, 17, 30, 45, 60, 73])
def test_the_pixels_outside_a_corner_stay(angle, compiled):
    """The 3 pixels nearest each corner of a square that lie at least half a pixel
    outside one of its edges (beyond an edge's end, or diagonally out) are not put on
    the square. (A pixel within half a pixel of both edges' lines is not placed by them:
    at 17 degrees the one diagonally out lies 0.04 pixel outside one edge's line, and the
    windows put it inside.)"""
    lab, u, v = _square(41, 11.3, angle)
    out = (np.maximum(np.abs(u), np.abs(v)) - 11.3 >= 0.5) & (lab == 0)
    for su, sv in product((-1, 1), repeat=2):
        corner = np.array([su * 11.3, sv * 11.3])
        d = np.where(out, np.hypot(u - corner[0], v - corner[1]), np.inf)
        for k in np.argsort(d, None)[:3]:
            r, c = np.unravel_index(k, lab.shape)
            post = planecut.edge_side(*_corner_case(lab, r, c), np.array([0]), np.array([1]),
                                      compiled)
            assert not post[0] > planecut.EDGE_P, (angle, r, c, post)


@pytest.mark.parametrize("compiled", [None, False])
@pytest.mark.parametrize("angle", [*range(0, 180, 15), 17, 37, 52, 98, 143])
def test_a_straight_edge_stays_where_it_is(angle, compiled):
    """Along one straight boundary at any angle, each pixel beside it (the others all
    detected, no photons' say of its own) stays on its side."""
    n = 31
    r, c = np.mgrid[0:n, 0:n] - n // 2
    a = np.deg2rad(angle)
    cat = (r * np.cos(a) - c * np.sin(a) > 0.3).astype(np.int64)
    edge = np.argwhere(np.abs(r * np.cos(a) - c * np.sin(a) - 0.3) < 1.5)
    edge = edge[(edge.min(1) >= 6) & (edge.max(1) < n - 6)]
    assert edge.shape[0] > 10
    for p in edge:
        A = cat[p[0], p[1]]
        post = planecut.edge_side(*_corner_case(cat, *p), np.array([A]), np.array([1 - A]),
                                  compiled)
        assert not post[0] > planecut.EDGE_P, (angle, p, post)


@pytest.mark.parametrize("compiled", [None, False])
def test_a_pixel_at_the_border_is_weighed_on_a_whole_window(compiled):
    """Three pixels of a straight edge's first row at the image's left border lean a
    nat each to the other side (what a background photon does), the rest of the edge
    3 nats each its own way. A window centred on the middle one, cut short by the
    border, lets lines turned a few steps cut the three off: it moves them. Moved in to
    hold all its pixels, the window weighs those lines against the pixels further
    along, as in the image's middle: it does not."""
    h, w = 21, 24
    r, c = np.mgrid[0:h, 0:w]
    cat = (r >= 10).astype(np.int64)              # A = 1 below, B = 0 above
    det = np.zeros((h, w), bool)
    weight = np.full((h, w), planecut.EDGE_FREE)
    one = np.array([1]), np.array([0])
    for cols in ((0, 1, 2), (10, 11, 12)):
        llr = np.zeros((h, w, 2))
        e = np.where(cat == 1, 3.0, -3.0)
        e[10, list(cols)] = -1.0
        llr[..., 1] = e
        who = np.array([[10, cols[1]]])
        post = planecut.edge_side(cat, weight, det, llr, who, *one, compiled)
        assert post[0] < planecut.EDGE_P, (cols, post)
        if cols[0] == 0:
            cut, _ = planecut._edge_window(cat, weight, det, llr, who, *one,
                                           planecut._edge_windows()[0], compiled)
            assert cut[0] > planecut.EDGE_P, cut
            want = _edge_brute(cat, weight, det, llr, (10, 1), 1, 0)
            np.testing.assert_allclose(post[0], want, atol=2e-4)


def _edge_brute(cat, weight, det, llr, p, A, B):
    """edge_side's posterior for one pixel, written out: the window centred on it where
    that is straight, else the straight ones of the 8 beside it where they all agree and
    two of them have lines EDGE_TURN apart, or lie on both sides of it (each centre a
    pixel or more from it) along each one's line. Its own window is centred on it, or
    moved in from the image's border until the window lies inside."""
    R = planecut.EDGE_R
    own = tuple(int(min(max(p[k], R), n - 1 - R) - p[k]) if n >= 2 * R + 1 else 0
                for k, n in enumerate(cat.shape))
    got, _ = _window_brute(cat, weight, det, llr, p, A, B, own)
    if np.isfinite(got):
        return got
    sh = planecut.EDGE_SHIFT
    cen = [(i, j) for i in (-sh, 0, sh) for j in (-sh, 0, sh) if i or j]
    said = [_window_brute(cat, weight, det, llr, p, A, B, x, planecut.EDGE_BESIDE_SPAN)
            for x in cen]
    ok = [k for k, x in enumerate(said) if np.isfinite(x[0])]
    if not ok:
        return np.nan
    posts = [said[k][0] for k in ok]
    if not (all(x > planecut.EDGE_P for x in posts)
            or all(x < 1 - planecut.EDGE_P for x in posts)):
        return np.nan
    K = planecut.EDGE_ANGLES
    for i in ok:
        for j in ok:
            if j <= i:
                continue
            turn = abs(said[i][1] - said[j][1])
            turn = min(turn, K - turn)
            across = True
            for k in (i, j):                      # along each window's line
                th = said[k][1] * np.pi / K
                ti = cen[i][0] * np.cos(th) - cen[i][1] * np.sin(th)
                tj = cen[j][0] * np.cos(th) - cen[j][1] * np.sin(th)
                across &= min(abs(ti), abs(tj)) >= 1.0 and ti * tj < 0
            if turn >= planecut.EDGE_TURN or across:
                return min(posts) if posts[0] > planecut.EDGE_P else max(posts)
    return np.nan


def _window_brute(cat, weight, det, llr, p, A, B, shift, span=None):
    """One window's posterior (centred at p + shift) written out: every direction, every
    split between two distinct projections (weighed by its width), both ways round
    (``span``: the directions within that many of the best line's only)."""
    R, K = planecut.EDGE_R, planecut.EDGE_ANGLES
    h, w = cat.shape
    qs = [(p[0] + shift[0] + i, p[1] + shift[1] + j) for i in range(-R, R + 1)
          for j in range(-R, R + 1)]
    inside = [0 <= r < h and 0 <= c < w for r, c in qs]
    lab = [cat[q] if ok else -1 for q, ok in zip(qs, inside, strict=True)]
    wt = [weight[q] if ok else 0.0 for q, ok in zip(qs, inside, strict=True)]
    ev = []
    for q, ok, lb in zip(qs, inside, lab, strict=True):
        if not ok:
            ev.append(0.0)
        elif det[q]:
            ev.append(planecut.EDGE_DET if lb == A else -planecut.EDGE_DET if lb == B else 0.0)
        elif np.isneginf(llr[q][A]) and np.isneginf(llr[q][B]):
            ev.append(0.0)
        else:
            ev.append(float(np.clip(llr[q][A] - llr[q][B], -planecut.EDGE_CAP,
                                    planecut.EDGE_CAP)))
    wt, lab, ev = np.array(wt), np.array(lab), np.array(ev)
    wa, wb = wt[lab == A].sum(), wt[lab == B].sum()
    off = np.array(qs) - np.array(p)
    best_misfit = np.inf
    scores, p_on_a, kk = [], [], []
    for k in range(K):
        th = k * np.pi / K
        proj = np.round(np.sin(th) * off[:, 0] + np.cos(th) * off[:, 1], 9)
        levels = np.unique(proj)
        cut = 0.5 * (levels[:-1] + levels[1:])                    # (splits,)
        for a_below in (True, False):
            on_a = (proj[None, :] < cut[:, None]) == a_below      # (splits, M)
            wrong = ((lab == A)[None, :] != on_a) & np.isin(lab, (A, B))[None, :]
            best_misfit = min(best_misfit, (wrong * wt).sum(1).min())
            scores.append((on_a * ev).sum(1) + np.log(np.diff(levels)))
            # (p at projection 0: its side of each split, inside the window or not)
            p_on_a.append((0.0 < cut) == a_below)
            kk.append(np.full(cut.size, k))
    if not (wa >= planecut.EDGE_MIN and wb >= planecut.EDGE_MIN
            and best_misfit <= planecut.EDGE_MISFIT):
        return np.nan, -1
    scores, p_on_a, kk = (np.concatenate(x) for x in (scores, p_on_a, kk))
    # the best line's direction: the first of (nearly) equals
    best = int(kk[scores >= scores.max() - 1e-9].min())
    gap = np.abs(kk - best)
    near = np.minimum(gap, K - gap) <= span if span is not None and span >= 0 else True
    z = np.exp(scores - scores.max()) * near
    return z[~p_on_a].sum() / z.sum(), best


def _random_edge_frame(seed, a=None):
    """Random labels near a line at ``a`` (random: None), a few flipped, some of no
    plane or a third, some pixels detected; evidence random, some -inf, some pixels
    -inf for both planes."""
    rng = np.random.default_rng(seed)
    h, w = 15, 17
    r, c = np.mgrid[0:h, 0:w]
    a = rng.uniform(0, np.pi) if a is None else a
    cat = (np.sin(a) * (r - 7) + np.cos(a) * (c - 8) > rng.uniform(-1, 1)).astype(np.int64)
    flip = rng.random((h, w)) < 0.04
    cat = np.where(flip, 1 - cat, cat)
    cat[rng.random((h, w)) < 0.03] = -1
    cat[rng.random((h, w)) < 0.03] = 2
    det = rng.random((h, w)) < 0.3
    weight = np.where(det, 1.0, planecut.EDGE_FREE)
    llr = rng.normal(0, 2, (h, w, 3))
    llr[rng.random((h, w, 3)) < 0.05] = -np.inf
    llr[rng.random((h, w)) < 0.03, :2] = -np.inf
    who = np.argwhere((cat >= 0) & ~det)[::3]
    A = cat[who[:, 0], who[:, 1]]
    return cat, weight, det, llr, who, A, np.where(A == 0, 1, 0)


@pytest.mark.parametrize("compiled", [None, False])
@pytest.mark.parametrize("seed,angle", [(0, None), (1, None), (2, None), (3, None),
                                        (4, 0.03), (5, np.pi - 0.03)])
def test_edge_side_is_its_sum_written_out(seed, angle, compiled):
    """edge_side's posterior (numba's and its numpy twin) against the sum over every
    line written out, on windows of random labels near a random line (and lines near 0
    and 180 degrees, where the directions wrap round), random evidence (some of it
    -inf, for one plane or both; some pixels detected) and pixels near the image's
    border (their own windows moved in); some pixels' own windows are not straight, and
    the windows beside them have the say."""
    cat, weight, det, llr, who, A, B = _random_edge_frame(seed, angle)
    got = planecut.edge_side(cat, weight, det, llr, who, A, B, compiled)
    own = planecut._own_window(cat, weight, det, llr, who, A, B, compiled)
    assert np.isfinite(got).sum() >= np.isfinite(own).sum()
    want = np.array([_edge_brute(cat, weight, det, llr, tuple(p), a_, b_)
                     for p, a_, b_ in zip(who, A, B, strict=True)])
    assert np.isfinite(got).sum() >= 5
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    ok = np.isfinite(want)
    np.testing.assert_allclose(got[ok], want[ok], atol=2e-4)


@pytest.mark.parametrize("compiled", [None, False])
@pytest.mark.parametrize("span", [None, 0, 1, 3])
def test_a_window_over_the_directions_near_its_best_line(span, compiled):
    """One window beside the pixel (numba's and the numpy twin) over the lines within
    ``span`` directions of its best line's (None: every direction), against the sum
    written out, on random frames (some directions wrap round 0 and 180 degrees)."""
    for seed, angle in [(0, None), (1, None), (4, 0.03), (5, np.pi - 0.03)]:
        cat, weight, det, llr, who, A, B = _random_edge_frame(seed, angle)
        win = planecut._edge_windows()[3]                      # centred (-5, 5) from p
        got, kd = planecut._edge_window(cat, weight, det, llr, who, A, B, win, compiled,
                                        span=span)
        want = [_window_brute(cat, weight, det, llr, tuple(p), a_, b_, win[4], span)
                for p, a_, b_ in zip(who, A, B, strict=True)]
        post = np.array([x[0] for x in want])
        np.testing.assert_array_equal(np.isnan(got), np.isnan(post))
        ok = np.isfinite(post)
        assert ok.sum() >= 3, (seed, ok.sum())
        np.testing.assert_allclose(got[ok], post[ok], atol=2e-4)
        np.testing.assert_array_equal(kd[ok], np.array([x[1] for x in want])[ok])


def test_the_random_frames_reach_both_kinds_of_window():
    """Among the frames above, pixels whose own window decides and pixels whose windows
    beside them do (their own not straight)."""
    own_said = beside_said = 0
    for seed, angle in [(0, None), (1, None), (2, None), (3, None), (4, 0.03),
                        (5, np.pi - 0.03)]:
        cat, weight, det, llr, who, A, B = _random_edge_frame(seed, angle)
        got = planecut.edge_side(cat, weight, det, llr, who, A, B, False)
        own = planecut._own_window(cat, weight, det, llr, who, A, B, False)
        own_said += np.isfinite(own).sum()
        beside_said += (np.isfinite(got) & np.isnan(own)).sum()
    assert own_said >= 10 and beside_said >= 5, (own_said, beside_said)


def test_threads_give_the_same_numbers():
    """edge_side's pixels and gauss_llr's rows in parts on two threads give what one
    thread gives, to the bit (a part's order or seam wrong would move a pixel's
    posterior to another's)."""
    for seed in (0, 1):
        cat, weight, det, llr, who, A, B = _random_edge_frame(seed)
        who, A, B = (np.concatenate([x] * 20) for x in (who, A, B))  # parts of >= 64
        rng = np.random.default_rng(seed)
        order = rng.permutation(who.shape[0])
        who, A, B = who[order], A[order], B[order]
        one = planecut.edge_side(cat, weight, det, llr, who, A, B, None, 1)
        two = planecut.edge_side(cat, weight, det, llr, who, A, B, None, 2)
        assert np.isfinite(one).sum() > 100
        np.testing.assert_array_equal(one, two)
    h, w, n, sb = 40, 6, 200, 2.3
    counts = rng.poisson(0.3, (h, w, n)).astype(float)
    P0 = np.concatenate([np.zeros((h, w, 1)), np.cumsum(counts, -1)], -1)
    beta = rng.uniform(0.2, 0.6, (h, w))
    T = rng.uniform(-10, n + 10, (h, w, 3))
    S = np.array([1.0, 2.0, 4.0])
    np.testing.assert_array_equal(planecut.gauss_llr(P0, beta, T, S, sb, None, 1),
                                  planecut.gauss_llr(P0, beta, T, S, sb, None, 3))


@pytest.mark.parametrize("compiled", [None, False])
def test_edge_side_is_the_same_on_the_frame_transposed(compiled):
    """Nothing follows the rows rather than the columns: on random frames and their
    transposes (the directions map onto each other), the same posteriors, the same
    pixels with none."""
    for seed in range(6, 16):
        cat, weight, det, llr, who, A, B = _random_edge_frame(seed)
        got = planecut.edge_side(cat, weight, det, llr, who, A, B, compiled)
        tr = planecut.edge_side(cat.T.copy(), weight.T.copy(), det.T.copy(),
                                llr.transpose(1, 0, 2).copy(), who[:, ::-1].copy(), A, B,
                                compiled)
        np.testing.assert_array_equal(np.isnan(got), np.isnan(tr))
        np.testing.assert_allclose(got[np.isfinite(got)], tr[np.isfinite(tr)], atol=1e-9)


@pytest.mark.parametrize("compiled", [None, False])
@pytest.mark.parametrize("angle", [0, 17, 30, 37, 52, 73, 98, 143])
def test_edge_side_puts_a_kink_back_on_its_line(angle, compiled):
    """A straight edge at any angle whose labels have one pixel on the wrong side, and
    whose photons each say little (1 nat each pixel for its side; the wrong pixel's
    own 0.8 nat for the wrong side): the line the window's photons place puts the pixel
    back (posterior of its true side > EDGE_P); the pixels rightly labelled stay."""
    n = 31
    r, c = np.mgrid[0:n, 0:n] - n // 2
    a = np.deg2rad(angle)
    d = r * np.cos(a) - c * np.sin(a) - 0.3
    truth = (d > 0).astype(np.int64)
    e = np.where(truth == 0, 1.0, -1.0)                           # A (0) against B (1)
    near = np.argwhere((np.abs(d) < 1.2) & (np.abs(r) < 6) & (np.abs(c) < 6))
    p = near[np.argmin(np.abs(d[near[:, 0], near[:, 1]] - 0.6))]  # B's, 0.6 px inside
    cat = truth.copy()
    cat[p[0], p[1]] = 0
    e[p[0], p[1]] = 0.8
    llr = np.stack([e / 2, -e / 2], -1)
    det = np.zeros(cat.shape, bool)
    weight = np.full(cat.shape, planecut.EDGE_FREE)
    got = planecut.edge_side(cat, weight, det, llr, p[None], np.array([0]), np.array([1]),
                             compiled)
    assert got[0] > planecut.EDGE_P, (angle, p, got)
    # its neighbours rightly labelled stay where they are
    who = near[(near != p).any(1)]
    A = cat[who[:, 0], who[:, 1]]
    post = planecut.edge_side(cat, weight, det, llr, who, A, 1 - A, compiled)
    assert np.all(post < planecut.EDGE_P), (angle, who[post >= planecut.EDGE_P])


def test_edge_side_leaves_corners_and_thin_frames():
    """A window that is no straight boundary (a square's corner) gets no posterior
    (NaN: left to the windows beside it); a frame too small for 6 of each label, none; no pixel
    asked, an empty answer; evidence of no photons at all (0 nats everywhere) leaves
    the pixel to chance between the sides, never a confident move."""
    lab, _, _ = _square(41, 11.3, 0)
    r = c = 20 - 11
    who = np.array([[r, c], [r - 1, c - 1], [r, c - 1]])
    A = lab[who[:, 0], who[:, 1]]
    llr = np.zeros(lab.shape + (2,))
    det = np.zeros(lab.shape, bool)
    weight = np.ones(lab.shape)
    got = planecut.edge_side(lab, weight, det, llr, who, A, 1 - A)
    assert np.isnan(got[0])
    for shape in [(1, 40), (40, 1), (2, 2), (3, 3)]:
        cat = np.zeros(shape, np.int64)
        cat[..., shape[-1] // 2:] = 1
        who = np.argwhere(np.ones(shape, bool))
        A = cat[who[:, 0], who[:, 1]]
        got = planecut.edge_side(cat, np.ones(shape), np.zeros(shape, bool),
                                 np.zeros(shape + (2,)), who, A, 1 - A)
        assert got.shape == (who.shape[0],) and np.all(np.isnan(got))
    got = planecut.edge_side(lab, weight, det, llr, np.zeros((0, 2), np.int64),
                             np.zeros(0, np.int64), np.zeros(0, np.int64))
    assert got.shape == (0,)
    n = 31
    rr, cc = np.mgrid[0:n, 0:n] - n // 2
    cat = (rr * np.cos(0.5) - cc * np.sin(0.5) > 0.3).astype(np.int64)
    who = np.argwhere(np.abs(rr * np.cos(0.5) - cc * np.sin(0.5) - 0.3) < 1.0)
    who = who[(who.min(1) >= 6) & (who.max(1) < n - 6)]
    A = cat[who[:, 0], who[:, 1]]
    got = planecut.edge_side(cat, np.full(cat.shape, 0.5), np.zeros(cat.shape, bool),
                             np.zeros((n, n, 2)), who, A, 1 - A)
    assert np.all(np.isfinite(got)) and np.all(got < planecut.EDGE_P)
