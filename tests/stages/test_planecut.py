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


@pytest.mark.parametrize("angle", [0, 10, 17, 30, 45, 60, 73])
def test_a_corner_pixel_goes_with_its_edges_at_any_angle(angle):
    """The pixel nearest each corner of a square, labelled as what surrounds it, is put
    back on the square: the windows beside it, along its edges, are each one straight
    boundary (misfit 0) and agree that it lies inside. The pixel is the one nearest the
    corner at least half a pixel inside both edges: a pixel the edge passes closer to
    is a tip its neighbours' centres cannot place (at 10 and 30 degrees the outermost
    pixels are 0.06 and 0.31 pixel inside, and the windows along their two edges
    disagree, so nothing is proposed)."""
    lab, u, v = _square(41, 11.3, angle)
    inside = 11.3 - np.maximum(np.abs(u), np.abs(v)) >= 0.5
    for su, sv in product((-1, 1), repeat=2):
        score = np.where(inside, su * u + sv * v, -np.inf)
        r, c = np.unravel_index(np.argmax(score), lab.shape)
        cat = lab.copy()
        cat[r, c] = 0
        pred, mis = planecut.straight(cat, np.ones(cat.shape), np.array([[r, c]]))
        assert pred[0] == 1 and mis[0] == 0.0, (r, c, pred, mis)


@pytest.mark.parametrize("angle", [0, 10, 30, 45, 60, 73])
def test_the_pixel_outside_a_corner_stays(angle):
    """The pixel diagonally outside each corner of a square, rightly what surrounds it, is
    not put on the square: no window beside it is one boundary with it inside."""
    lab, u, v = _square(41, 11.3, angle)
    for su, sv in product((-1, 1), repeat=2):
        score = np.where(lab == 1, su * u + sv * v, -np.inf)
        r, c = np.unravel_index(np.argmax(score), lab.shape)
        out = np.where(lab == 0, np.hypot(u - u[r, c], v - v[r, c])
                       + 10 * ((su * u < su * u[r, c]) | (sv * v < sv * v[r, c])), np.inf)
        ro, co = np.unravel_index(np.argmin(out), lab.shape)
        pred, mis = planecut.straight(lab, np.ones(lab.shape), np.array([[ro, co]]))
        assert not (pred[0] == 1 and mis[0] <= planecut.STRAIGHT_MISFIT), (ro, co)


@pytest.mark.parametrize("angle", [*range(0, 180, 15), 17, 37, 52, 98, 143])
def test_a_straight_edge_is_left_to_the_sweeps(angle):
    """Along one straight boundary (at any angle) no pixel is moved: the window centred
    on it is the boundary, so :func:`straight` proposes nothing, or (where the edge lies
    between two of the 36 directions and the centred window's split misfits, as at 52
    degrees) the windows beside it put the pixel back on its own side."""
    n = 31
    r, c = np.mgrid[0:n, 0:n] - n // 2
    a = np.deg2rad(angle)
    cat = (r * np.cos(a) - c * np.sin(a) > 0.3).astype(np.int64)
    edge = np.argwhere(np.abs(r * np.cos(a) - c * np.sin(a) - 0.3) < 1.5)
    edge = edge[(edge.min(1) >= 6) & (edge.max(1) < n - 6)]
    pred, _ = planecut.straight(cat, np.ones(cat.shape), edge)
    assert edge.shape[0] > 10
    assert np.all((pred == -1) | (pred == cat[edge[:, 0], edge[:, 1]]))
    assert np.mean(pred == -1) > 0.8


@pytest.mark.parametrize("shape", [(1, 40), (40, 1), (2, 2), (3, 3)])
def test_straight_on_frames_too_small_for_a_window(shape):
    """Frames too small or too thin for a window with 6 pixels of each label: no pixel
    is moved, nothing raised; no pixel asked: empty answers; no label at all: none."""
    cat = np.zeros(shape, np.int64)
    cat[..., shape[-1] // 2:] = 1
    who = np.argwhere(np.ones(shape, bool))
    pred, mis = planecut.straight(cat, np.ones(shape), who)
    assert pred.shape == (who.shape[0],)
    assert np.all((pred == -1) | (pred == cat[who[:, 0], who[:, 1]]))  # nothing moves
    pred, mis = planecut.straight(cat, np.ones(shape), np.zeros((0, 2), np.int64))
    assert pred.shape == (0,) and mis.shape == (0,)
    pred, _ = planecut.straight(np.full(shape, -1), np.ones(shape), who)
    assert np.all(pred == -1)
