"""The edges as whole lines (stages/ranging/edgelines.py): the boundary points and runs on
label images drawn here, the line's posterior against a sum written out, a wrong label
beside a long edge and beyond a corner put right, and the guards (detected pixels, far
pixels, noise, a pixel sent two ways, frames too small or empty); a detection its edge's
line refuses, doubted by the odds written out."""

import numpy as np
import pytest

from stages.ranging import edgelines as el

CAP, DET = 6.0, 12.0


def _frame(truth, say=3.0, rng=None, noise=0.0):
    """(cat, weight, dets, lp) for labels ``truth`` (h, w; 0 or 1): each pixel's own
    log-likelihood ratio ``say`` nats for its true plane against the other (plus
    Gaussian ``noise``), and its true plane's ``say`` against no surface."""
    h, w = truth.shape
    e = np.where(truth == 0, say, -say).astype(np.float64)
    if noise:
        e = e + rng.normal(0, noise, e.shape)
    lp = np.stack([e, np.zeros_like(e)], -1) + np.where(truth == 1, say, 0.0)[..., None]
    return (truth.copy(), np.full((h, w), 0.5), np.zeros((h, w), bool), lp)


def _half(h, w, col):
    return (np.arange(w)[None, :] >= col).astype(np.int64).repeat(h, 0)


def test_boundary_points_between_planes_only():
    cat = _half(4, 6, 3)
    cat[0, :] = -1
    pts = el.boundary_points(cat)
    assert list(pts) == [(0, 1)]
    assert np.allclose(pts[(0, 1)], [[r, 2.5] for r in (1, 2, 3)])
    assert el.boundary_points(np.full((3, 3), -1)) == {}


def test_a_staircase_at_30_degrees_is_one_run():
    """The boundary of a half-plane at 30 degrees: one run along it, its normal within a
    degree, its extent the image's."""
    h = w = 40
    r, c = np.mgrid[0:h, 0:w]
    a = np.deg2rad(30.0)
    truth = ((r - 20) * np.cos(a) + (c - 20) * np.sin(a) > 0.3).astype(np.int64)
    got = el.runs(el.boundary_points(truth)[(0, 1)])
    assert len(got) == 1
    n, tan, centre, t0, t1 = got[0]
    assert abs(abs(n @ [np.cos(a), np.sin(a)]) - 1.0) < 1 - np.cos(np.deg2rad(1.0))
    assert t1 - t0 > 35


def test_a_gap_splits_a_run_and_scatter_makes_none():
    pts = np.array([[r + 0.5, 7.0] for r in list(range(10)) + list(range(16, 26))])
    got = el.runs(pts)
    assert len(got) == 2 and sorted(round(g[4] - g[3]) for g in got) == [9, 9]
    rng = np.random.default_rng(3)
    assert el.runs(rng.uniform(0, 60, (40, 2))) == []


def _pieces(cuts_xy, centre, normals):
    """Every line a run weighs, written out: at each tilt (``normals``) the offsets in
    +-``LINE_SHIFT`` cut where they pass a point of ``cuts_xy``, each piece by its
    middle and its length: [(normal, offset, length)]."""
    out = []
    for nn in normals:
        d = [float((x - centre) @ nn) for x in cuts_xy]
        b = sorted({min(max(v, -el.LINE_SHIFT), el.LINE_SHIFT) for v in d}
                   | {-el.LINE_SHIFT, el.LINE_SHIFT})
        out += [(nn, 0.5 * (lo + hi), hi - lo) for lo, hi in zip(b[:-1], b[1:], strict=True)]
    return out


def _side(x, centre, nn, o, a_pos):
    return bool(((x - centre) @ nn > o) == a_pos)


def test_the_posterior_is_the_sum_written_out():
    """A line's posterior weights of its distinct sides of some pixels (``_patterns``,
    those pixels' own say taken out of the line's evidence) against the integral over
    every tilt and offset written out by loops (each piece of offsets between two
    pixels' distances by its middle and its length), pixel by pixel."""
    rng = np.random.default_rng(5)
    pts = np.array([[r + 0.5, 7.5] for r in range(12)], float)
    n, tan, centre, t0, t1 = el.runs(pts)[0]
    xy = np.array([[r, c] for r in range(12) for c in range(4, 11)], float)
    q = (xy[:, 0] * 11 + xy[:, 1]).astype(np.int64)
    e = rng.normal(0, 2.0, len(xy))
    phi = np.arctan2(n[1], n[0]) + el.tilts(t1 - t0)
    normals = np.stack([np.cos(phi), np.sin(phi)], -1)
    a_pos = False
    line = el._Line(0, 1, tan, centre, t0, t1, a_pos, normals, (normals[0], 0.0), (q, e))
    X = np.stack(np.mgrid[0:12, 0:11], -1).reshape(-1, 2).astype(np.float64)
    J = np.sort(q[rng.choice(len(q), 10, replace=False)])
    pat, lw = el._patterns(line, J, X)
    w = np.exp(lw - lw.max())
    got = (w[:, None] * pat).sum(0) / w.sum()
    out = ~np.isin(q, J)
    num, den = np.zeros(len(J)), 0.0
    for nn, o, length in _pieces(xy, centre, normals):
        ll = sum(e[k] for k in np.nonzero(out)[0] if _side(xy[k], centre, nn, o, a_pos))
        wt = np.exp(ll) * length
        den += wt
        num += wt * np.array([_side(X[j], centre, nn, o, a_pos) for j in J])
    assert np.allclose(got, num / den)
    assert len(pat) == len({tuple(p) for p in pat.tolist()})      # each side once


@pytest.mark.parametrize("convex", [True, False])
def test_a_corners_posterior_is_the_sum_over_both_lines_written_out(convex):
    """A corner's two lines (a box's left and top edges) with random says: the
    posterior of A's side of each zone pixel (``_corner``) against the sum over every
    pair of lines (tilt, offset each), written out by broadcasting: each line's
    evidence without the pixels near both, and those pixels' say once, on A's side
    where both lines put them (convex) or either (concave)."""
    rng = np.random.default_rng(8)
    h, w = 24, 24
    X = np.stack(np.mgrid[0:h, 0:w], -1).reshape(-1, 2).astype(np.float64)
    say_all = rng.normal(0, 2.0, h * w)
    lines = []
    for pts in (np.array([[r + 0.5, 5.5] for r in range(6, 18)]),     # left edge
                np.array([[5.5, c + 0.5] for c in range(6, 18)])):    # top edge
        n, tan, centre, t0, t1 = el.runs(pts)[0]
        q = np.nonzero(np.abs((X - centre) @ n) <= el.LINE_BAND)[0]
        phi = np.arctan2(n[1], n[0]) + el.tilts(t1 - t0)
        normals = np.stack([np.cos(phi), np.sin(phi)], -1)
        a_pos = bool((np.array([12.0, 12.0]) - centre) @ n > 0)       # A: the box
        lines.append(el._Line(0, 1, tan, centre, t0, t1, a_pos, normals,
                              (normals[0], 0.0), (q, say_all[q])))
    l1, l2 = lines
    zr, zc = np.mgrid[3:9, 3:9]
    Z = np.sort((zr * w + zc).ravel())
    J = np.union1d(Z, np.intersect1d(l1.q, l2.q))
    got = el._corner(l1, l2, Z, J, convex, X, say_all[J])
    # written out: every pair of lines at once, each line's pieces of offsets cut by
    # its band's and the zone's pixels
    sides = []
    for ln in (l1, l2):
        inb = np.isin(ln.q, J)
        pieces = _pieces(X[np.union1d(ln.q, J)], ln.centre, ln.normals)
        nn = np.array([x[0] for x in pieces])
        o, length = (np.array([x[i] for x in pieces]) for i in (1, 2))

        def sides_of(pts, ln=ln, nn=nn, o=o):
            return ((pts - ln.centre) @ nn.T > o) == ln.a_pos                  # (pts, K)

        a = sides_of(X[J])
        ll = say_all[ln.q[~inb]] @ sides_of(X[ln.q[~inb]]).astype(float)
        sides.append((a, ll + np.log(length)))
    (a1, e1), (a2, e2) = sides
    on = (a1[:, :, None] & a2[:, None, :]) if convex else (a1[:, :, None] | a2[:, None, :])
    L = e1[:, None] + e2[None, :] + np.einsum("j,jab->ab", say_all[J], on.astype(float))
    post = np.exp(L - L.max())
    post /= post.sum()
    want = np.einsum("ab,jab->j", post, on.astype(float))[np.searchsorted(J, Z)]
    assert np.allclose(got, want, atol=1e-12)


def test_a_wrong_label_beside_a_long_edge_moves_back():
    """Two pixels one column over on a 30-row edge whose own photons lean the wrong way
    (1 nat): the edge's other 28 rows place them."""
    truth = _half(30, 20, 10)
    cat, weight, dets, lp = _frame(truth)
    for r in (9, 17):
        cat[r, 9] = 1
        lp[r, 9, 0] = -1.0
    q, pl = el.line_moves(cat, weight, dets, lp, CAP, DET)[:2]
    assert sorted(q.tolist()) == [9 * 20 + 9, 17 * 20 + 9] and (pl == 0).all()


def test_detected_and_far_pixels_stay():
    truth = _half(30, 20, 10)
    cat, weight, dets, lp = _frame(truth)
    cat[9, 9], dets[9, 9] = 1, True          # a detected pixel: never moved
    cat[17, 7] = 1                           # three columns off the line: not the line's
    lp[17, 7, 0] = -1.0
    q, _, qd, _, _ = el.line_moves(cat, weight, dets, lp, CAP, DET)[:5]
    assert 9 * 20 + 9 not in q and 17 * 20 + 7 not in q
    assert 17 * 20 + 7 not in qd


def _line_odds(cat, dets, say_of, pix, det_w):
    """The log-odds that ``pix`` lies on plane 0's side of the frame's one run, every
    pixel of the frame in its band, integrated over every tilt and offset by loops (each
    piece of offsets between two pixels' distances by its middle and its length): each
    undetected pixel's say clipped, each detected one's +-``det_w``, ``pix``'s left out."""
    n, tan, centre, t0, t1 = el.runs(el.boundary_points(cat)[(0, 1)])[0]
    h, w = cat.shape
    a_side = (np.array([0.0, 0.0]) - centre) @ n > 0      # plane 0 holds column 0
    phi = np.arctan2(n[1], n[0]) + el.tilts(t1 - t0)
    normals = np.stack([np.cos(phi), np.sin(phi)], -1)
    every = np.stack(np.mgrid[0:h, 0:w], -1).reshape(-1, 2).astype(np.float64)
    on, off = [], []
    for nn, o, length in _pieces(every, centre, normals):
        ll, pix_on_a = np.log(length), None
        for r in range(h):
            for c in range(w):
                on_a = (((np.array([r, c]) - centre) @ nn > o) == a_side)
                if (r, c) == pix:
                    pix_on_a = on_a
                elif on_a:
                    ll += ((det_w if cat[r, c] == 0 else -det_w) if dets[r, c]
                           else say_of(r, c))
        (on if pix_on_a else off).append(ll)
    lse = lambda x: max(x) + np.log(np.sum(np.exp(np.array(x) - max(x))))  # noqa: E731
    return lse(on) - lse(off)


@pytest.mark.parametrize("own", [1.0, 4.0, 30.0])
def test_a_detection_its_line_refuses_is_doubted_by_the_odds_written_out(own):
    """A detected pixel one column over on a 14-row edge, its own photons ``own`` nats
    for the plane it was detected on: it is doubted where its whole log-likelihood ratio
    and the line's log-odds without it (written out here) put it on the other plane, and
    the chance it is where it was detected is the posterior's."""
    rng = np.random.default_rng(11)
    truth = _half(14, 6, 3)
    cat, weight, dets, lp = _frame(truth, say=1.5, rng=rng, noise=0.7)
    pix = (7, 2)
    cat[pix], dets[pix] = 1, True
    lp[pix] = (0.0, own)

    def say_of(r, c):
        return float(np.clip(lp[r, c, 0] - lp[r, c, 1], -CAP, CAP))

    z = _line_odds(cat, dets, say_of, pix, el.LINE_DET) - own
    p_was = 1.0 / (1.0 + np.exp(z))
    q, _, qd, pld, got = el.line_moves(cat, weight, dets, lp, CAP, el.LINE_DET)[:5]
    assert pix[0] * 6 + pix[1] not in q                  # never moved as an undetected one
    if p_was < 1.0 - el.LINE_P_DET:
        assert qd.tolist() == [pix[0] * 6 + pix[1]] and pld.tolist() == [0]
        assert got[0] == pytest.approx(p_was, rel=1e-6, abs=1e-12)
    else:
        assert qd.size == 0
    assert (own < 10) == (qd.size == 1)                  # (the line's odds: ~ 10 nats)


@pytest.mark.parametrize("label, say, own", [(1, 0.5, -4.0), (1, 0.2, -3.0), (0, 0.5, -4.0)])
def test_an_undetected_pixel_moves_where_the_odds_written_out_favour_the_other_side(
        label, say, own):
    """An undetected pixel one column over on a 14-row edge, on plane 0's side, labelled
    ``label``, its own photons ``own`` nats for plane 0 (the others ``say`` with noise):
    the line's posterior of plane 0's side (the line's log-odds without it, written out
    here, and its own clipped say) is what the lines report for it, and it moves where
    the other side's posterior is above ``LINE_P`` (0.5, the Bayes decision for the
    squared error), or stays. Labelled 1, the posteriors are 0.915 and 0.616 (the offsets
    integrated; 0.91 and 0.60 on a grid 0.01 px apart, 0.897 and 0.60 on one 0.05 apart):
    it moves (the second did not at the cut of 0.9 before); labelled 0, it stays."""
    rng = np.random.default_rng(11)
    truth = _half(14, 6, 3)
    cat, weight, dets, lp = _frame(truth, say=say, rng=rng, noise=0.7)
    pix = (7, 2)
    cat[pix] = label
    lp[pix] = (own, 0.0)

    def say_of(r, c):
        return float(np.clip(lp[r, c, 0] - lp[r, c, 1], -CAP, CAP))

    p0 = 1.0 / (1.0 + np.exp(-(_line_odds(cat, dets, say_of, pix, DET) + say_of(*pix))))
    got = el.line_moves(cat, weight, dets, lp, CAP, DET)
    k = pix[0] * 6 + pix[1]
    seen = got.seen_q == k
    assert seen.sum() == 1 and got.seen_a[seen] == 0 and got.seen_b[seen] == 1
    assert got.seen_p_a[seen][0] == pytest.approx(p0, rel=1e-6, abs=1e-12)
    assert (k in got.q) == (label == 1) == ((p0 if label == 1 else 1.0 - p0) > el.LINE_P)
    assert got.pl[got.q == k].tolist() == ([0] if label == 1 else [])
    assert label == 0 or p0 < (0.7 if say < 0.5 else 0.95)


def test_a_pixel_a_corner_weighed_is_the_corners():
    """A box of plane 0 (its corner convex), pixel (11, 8) beside its top-left corner
    rightly labelled 0, its own photons leaning 4.5 nats to plane 1. The left edge's line
    alone, carried on past the corner, puts it on plane 1 with about 0.6; the corner, both
    lines together, on plane 0 with 0.577 (the offsets integrated; 0.588 and 0.63 with
    the line's offsets on grids 0.01 and 0.05 px apart).
    The corner's posterior is the pixel's: one record, and it stays (an outside review
    found it moved by the line's record)."""
    r, c = np.mgrid[0:40, 0:32]
    truth = ((r >= 10) & (r < 30) & (c >= 8) & (c < 22)).astype(np.int64) ^ 1
    cat, weight, dets, lp = _frame(truth, say=1.0)
    lp[11, 8] = (-4.5, 0.0)
    got = el.line_moves(cat, weight, dets, lp, CAP, DET)
    k = 11 * 32 + 8
    assert got.seen_p_a[got.seen_q == k] == pytest.approx([0.577], abs=0.005)
    assert k not in got.q


def test_a_corner_holds_only_its_own_pair():
    """A box of plane 2 on a wall (0) below a band of plane 1 (rows 0-4), the box's
    top-left corner two rows below the band's edge. A pixel of the band labelled as
    the wall (its own photons leaning 1 nat to the wall) lies in the box corner's zone
    (the corner's crossing half a pixel above the box's first row, 6.5 as it rounds),
    but that corner weighs the wall against the box only: the band's edge (pair 0, 1)
    still moves it (the first version of the corners' precedence did not: the scene
    turned by 10 degrees, its floor under the board)."""
    h, w = 40, 40
    r, c = np.mgrid[0:h, 0:w]
    truth = np.where(r < 5, 1, 0)
    truth = np.where((r >= 7) & (r < 22) & (c >= 10) & (c < 26), 2, truth)
    lp = np.where(truth[..., None] == np.arange(3), 3.0, 0.0)
    cat = truth.copy()
    cat[4, 10] = 0
    lp[4, 10] = (1.0, 0.0, 0.0)
    zones = []
    corner = el._corner

    def spy(l1, l2, Z, *rest):
        zones.append((l1.A, l1.B, Z))
        return corner(l1, l2, Z, *rest)

    k = 4 * w + 10
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(el, "_corner", spy)
        got = el.line_moves(cat, np.full((h, w), 0.5), np.zeros((h, w), bool), lp, CAP, DET)
    assert any(k in Z for A, B, Z in zones if (A, B) == (0, 2))     # in the corner's zone
    assert got.pl[got.q == k].tolist() == [1]


@pytest.mark.parametrize("inside", [1, 0])
def test_the_pixel_past_a_box_corner(inside):
    """A box (rows 10-29, cols 8-21) in a 40 x 32 frame; the pixel diagonal to its
    top-left corner labelled as the box, its own photons leaning to the box. The box's
    left and top edges cross at the corner, and the pixel lies outside both: it goes
    back. Labels swapped (the box plane 0, its surround 1): the corner is then the
    surround's concave one, the same pixel moves."""
    r, c = np.mgrid[0:40, 0:32]
    box = (r >= 10) & (r < 30) & (c >= 8) & (c < 22)
    truth = np.where(box, inside, 1 - inside).astype(np.int64)
    cat, weight, dets, lp = _frame(truth)
    cat[9, 7] = truth[10, 8]
    lp[9, 7, :] = lp[10, 8, :] / 3.0
    q, pl = el.line_moves(cat, weight, dets, lp, CAP, DET)[:2]
    assert q.tolist() == [9 * 32 + 7] and pl.tolist() == [truth[9, 7]]


def test_noisy_labels_make_no_line():
    rng = np.random.default_rng(2)
    cat = rng.integers(0, 2, (30, 30))
    _, weight, dets, lp = _frame(cat, rng=rng, noise=1.0)
    q = el.line_moves(cat, weight, dets, lp, CAP, DET)[0]
    assert q.size == 0


@pytest.mark.parametrize("shape", [(1, 256), (3, 3), (0, 0), (64, 64)])
def test_small_empty_and_planeless_frames(shape):
    cat = np.full(shape, -1, np.int64)
    lp = np.zeros(shape + (1,))
    got = el.line_moves(cat, np.ones(shape), np.zeros(shape, bool), lp, CAP, DET)
    assert all(x.size == 0 for x in got)
    if shape == (1, 256):
        cat = _half(1, 256, 100)
        _, weight, dets, lp = _frame(cat)
        assert el.line_moves(cat, weight, dets, lp, CAP, DET)[0].size == 0


def test_a_pixel_sent_two_ways_stays():
    q, pl = el.one_plane([5, 3, 5, 7, 7], [1, 2, 0, 4, 4])
    assert q.tolist() == [3, 7] and pl.tolist() == [2, 4]


def test_nan_and_minus_inf_likelihoods_have_no_say():
    """NaN and -inf - -inf inside the band (columns 7-12) count as no say."""
    truth = _half(30, 20, 10)
    cat, weight, dets, lp = _frame(truth)
    lp[20:, 8, 0] = np.nan
    lp[:5, 11, :] = -np.inf
    cat[12, 9] = 1
    lp[12, 9, 0] = -1.0
    q, pl = el.line_moves(cat, weight, dets, lp, CAP, DET)[:2]
    assert q.tolist() == [12 * 20 + 9] and pl.tolist() == [0]


def test_a_run_reaches_the_border_when_it_ends_near_it():
    """A run that stops 3 pixels short of the image's left border moves its pixels on to
    the border (no corner fits between); one that stops 10 short, only inside it."""
    centre, tan = np.array([48.5, 30.0]), np.array([0.0, 1.0])
    assert el._reach(centre, tan, 3.0, 63.0, 64, 64) == (-0.5, 63.5)
    assert el._reach(centre, tan, 10.0, 50.0, 64, 64) == (11.0, 49.0)
    a = np.deg2rad(30.0)
    tan = np.array([np.sin(a), np.cos(a)])
    c0 = 32.0 * tan.sum()                 # the centre's place along the line
    lo, hi = el._reach(np.array([32.0, 32.0]), tan, c0 - 35.0, c0 + 35.0, 64, 64)
    # at 30 degrees the line leaves through the left and right borders (cols -0.5, 63.5),
    # 37.5 and 36.4 from the centre along it: within 6 of the run's ends
    assert lo == pytest.approx(c0 - 32.5 / np.cos(a))
    assert hi == pytest.approx(c0 + 31.5 / np.cos(a))
    assert el._reach(np.array([32.0, 32.0]), tan, c0 - 20.0, c0 + 20.0, 64, 64) == (
        pytest.approx(c0 - 19.0), pytest.approx(c0 + 19.0))


def test_the_first_pixels_at_the_border_move():
    """Two pixels at the left border, one row over, their photons silent (no signal
    photon): the run starts beside them, and the line carries on to the border. (Were
    their photons to lean the wrong way, the lines turned a little that cut them off
    alone would keep them: a run's last pixels are weighed by their own photons too.)"""
    truth = (np.arange(30)[:, None] >= 15).astype(np.int64).repeat(40, 1)
    cat, weight, dets, lp = _frame(truth)
    for c in (0, 1):
        cat[15, c] = 0
        lp[15, c, :] = 0.0
    q, pl = el.line_moves(cat, weight, dets, lp, CAP, DET)[:2]
    assert sorted(q.tolist()) == [15 * 40, 15 * 40 + 1] and (pl == 1).all()


def test_two_boxes_whose_edges_cross_make_no_corner():
    """Two boxes of one plane, the first's right edge and the second's top edge crossing
    near both runs' ends (an outside review's case): the labels around the crossing
    are no corner, and no pixel, all rightly labelled, moves (67 did before the zone's
    labels had to fit the corner)."""
    r, c = np.mgrid[0:56, 0:48]
    truth = np.where(((r < 20) & (c < 10)) | ((r >= 24) & (r < 44) & (c >= 14) & (c < 34)),
                     0, 1).astype(np.int64)
    cat, weight, dets, lp = _frame(truth)
    q = el.line_moves(cat, weight, dets, lp, CAP, DET)[0]
    assert q.size == 0


def test_labels_in_the_sky_do_not_drop_a_line():
    """A post (plane 1) before a wall (plane 0), sky to its right: the sky's pixels hold
    the labels their neighbours gave them (the wall's, and the post's in a few of the
    band's pixels) and photons that favour neither plane over no surface. They do not
    count in the line's misfit: the post's right edge stands, and a pixel of the post
    beside it labelled as the wall goes back (with the sky's labels counted, the misfit
    is over 5 % and the line is dropped)."""
    h, w = 30, 30
    r, c = np.mgrid[0:h, 0:w]
    post = (c >= 5) & (c < 15)
    sky = c >= 15
    cat, weight, dets, lp = _frame(post.astype(np.int64))
    cat[sky & (c >= 16) & (c <= 17) & (np.random.default_rng(4).random((h, w)) < 0.3)] = 1
    lp[sky] = -0.5
    cat[12, 14] = 0
    lp[12, 14] = (0.5, -0.5)          # its own photons lean a nat to the wall
    q, pl = el.line_moves(cat, weight, dets, lp, CAP, DET)[:2]
    assert 12 * w + 14 in q.tolist() and pl[q.tolist().index(12 * w + 14)] == 1


def test_a_detection_is_not_doubted_towards_a_plane_outside_the_window():
    """The line puts the detected pixel on plane 0, but plane 0's pulse lies outside the
    window there (its log-likelihood -inf): the detection stands."""
    truth = _half(14, 6, 3)
    cat, weight, dets, lp = _frame(truth, say=1.5)
    cat[7, 2], dets[7, 2] = 1, True
    lp[7, 2] = (0.0, 1.0)
    assert el.line_moves(cat, weight, dets, lp, CAP, el.LINE_DET)[2].tolist() == [44]
    lp[7, 2] = (-np.inf, 1.0)
    assert el.line_moves(cat, weight, dets, lp, CAP, el.LINE_DET)[2].size == 0


def _exact_p_a(X, say, centre, phis, a_pos):
    """Each point's posterior of A's side under a uniform prior over the lines' tilts
    ``phis`` (their normals' angles) and a continuous offset in +-``LINE_SHIFT``: at
    each tilt the log-evidence is constant on each piece of offsets between the points'
    distances (``_pieces``), so the integral over the offset is exact (each piece's
    evidence times its length)."""
    lls, ws, ons = [], [], []
    for phi in phis:
        nn = np.array([np.cos(phi), np.sin(phi)])
        pieces = _pieces(X, centre, [nn])
        mid = np.array([o for _, o, _ in pieces])
        on = ((((X - centre) @ nn)[None, :] > mid[:, None]) == a_pos).astype(np.float64)
        lls.append(on @ say)                                      # (pieces, m) -> (pieces,)
        ws.append(np.array([length for *_, length in pieces]))
        ons.append(on)
    top = max(x.max() for x in lls)
    acc, tot = np.zeros(len(X)), 0.0
    for ll, w, on in zip(lls, ws, ons, strict=True):
        p = np.exp(ll - top) * w
        acc += p @ on
        tot += p.sum()
    return acc / tot


def test_the_lines_posterior_is_the_integral_over_lines(monkeypatch):
    """A half-plane's edge across a 64 x 64 frame at 12 degrees, whose pixels come within
    hundredths of a pixel of it (0.007 px), each pixel's photons 2 nats for its true
    plane give or take 2: the posterior the lines report for each pixel they weigh
    against the integral over every line (``_exact_p_a``, written apart): over the same
    tilts the same to 1e-9 (the offset is integrated exactly); over tilts five times
    finer, within 0.013 (a grid of offsets 0.05 px apart missed it by 0.097, 0.01 apart
    by 0.013: the outside probe's edge at 12 degrees put pixels 0.007-0.03 px from it on
    the far plane at posteriors of 0.004-0.01 that the integral makes 0.13-0.47). At 33
    degrees the tilts' step leaves 0.19 (docs/ranging.md)."""
    seen = []

    class Rec(el._Line):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            seen.append(self)

    monkeypatch.setattr(el, "_Line", Rec)
    h = w = 64
    r, c = np.mgrid[0:h, 0:w]
    a = np.deg2rad(12.0)
    truth = ((r + 0.5 - 32) * np.cos(a) - (c + 0.5 - 32) * np.sin(a) > 0).astype(np.int64)
    cat, weight, dets, lp = _frame(truth, say=2.0, rng=np.random.default_rng(11), noise=2.0)
    got = el.line_moves(cat, weight, dets, lp, CAP, DET)
    (line,) = seen
    X = np.stack([line.q // w, line.q % w], -1).astype(np.float64)
    k = np.searchsorted(line.q, got.seen_q)
    assert got.seen_q.size > 50 and np.array_equal(line.q[k], got.seen_q)
    phi = np.arctan2(line.normals[:, 1], line.normals[:, 0])
    same = _exact_p_a(X, line.say, line.centre, phi, line.a_pos)
    assert np.allclose(got.seen_p_a, same[k], rtol=0, atol=1e-9)
    fine = np.linspace(phi[0], phi[-1], 5 * (len(phi) - 1) + 1)
    want = _exact_p_a(X, line.say, line.centre, fine, line.a_pos)
    assert np.abs(got.seen_p_a - want[k]).max() < 0.05


def test_a_clean_box_has_four_edges_and_four_corners():
    """A box of 16 x 14 pixels, every pixel's photons 3 nats for its true plane: each
    edge is a line (the misfit counts the run's own pixels: past its ends, at a corner,
    the band holds the other edge's pixels, and the top edge misfit its exact line by
    6 %), the four corners form, each crossing within a pixel of the box's (the band
    reaches half a pixel past a run's end, where the other edge's pixels lie on the
    far plane: their photons tilt a line by a degree or two), and no pixel moves."""
    h, w = 30, 32
    r, c = np.mgrid[0:h, 0:w]
    truth = ((r >= 8) & (r < 24) & (c >= 10) & (c < 24)).astype(np.int64)
    cat, weight, dets, lp = _frame(truth)
    crossings = []
    corner = el._corner

    def spy(l1, l2, Z, *rest):
        crossings.append(np.linalg.solve(np.stack([l1.n_map, l2.n_map]),
                                         [l1.rho_map, l2.rho_map]))
        return corner(l1, l2, Z, *rest)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(el, "_corner", spy)
        got = el.line_moves(cat, weight, dets, lp, CAP, DET)
    assert got.q.size == 0
    want = [(7.5, 9.5), (7.5, 23.5), (23.5, 9.5), (23.5, 23.5)]
    assert len(crossings) == 4
    for x in crossings:
        assert min(np.hypot(*(x - np.array(p))) for p in want) < 1.0
