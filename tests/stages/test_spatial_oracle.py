"""The spatial benchmark's scene with its edges as arguments, and the edges' oracle
(benchmarks/spatial_oracle.py: how far any estimator can place an edge)."""

from __future__ import annotations

import hashlib
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import poisson

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks import spatial_oracle as so  # noqa: E402
from benchmarks.spatial_scenes import EDGES, N_BINS, histograms, scene  # noqa: E402


def test_the_scene_moves_one_edge_and_no_other():
    """No edge moved: the scene as it was before its edges were arguments (a digest of
    the grid's scene from then; the turned one's sums, its turn by the C library's
    sine). The box's top edge a pixel down: only the box's first row changes, to the
    wall behind it."""
    base = scene()
    digest = hashlib.sha256(np.nan_to_num(base.depth, nan=-1.0).tobytes()
                            + base.share.tobytes()).hexdigest()
    assert digest == "9ccf7dab91e43cc1a393c18a12751b3ca3724797f3167230049775158b96149a"
    turned = scene(angle_deg=30)
    assert np.isnan(turned.depth).sum() == 4427 and turned.share.sum() == 4096.0
    np.testing.assert_allclose(np.nansum(turned.depth), 20177.636622140955, rtol=1e-12)
    same = scene(edges=dict(EDGES))
    np.testing.assert_array_equal(base.depth, same.depth)
    moved = scene(edges={"box_r0": EDGES["box_r0"] + 1 / 64})
    diff = ~np.isclose(base.depth, moved.depth, equal_nan=True).all(-1)
    rows, cols = np.nonzero(diff)
    assert set(rows) == {20} and cols.min() == 8 and cols.max() == 25
    np.testing.assert_allclose(base.depth[20, 8:26, 0], 3.0)
    assert (moved.depth[20, 8:26, 0] > 6.0).all()
    with pytest.raises(ValueError, match="no such edge"):
        scene(edges={"box_top": 0.3})


def test_the_likelihood_is_poissons():
    """The oracle's log-likelihood of a pixel's histogram against scipy's Poisson pmf
    over the bins (the same rate a bin: the background flat, the pulse over each bin),
    for a surface, two, and none: the same up to a constant of the counts."""
    rng = np.random.default_rng(3)
    counts = rng.poisson(0.2, (4, N_BINS))
    depth = np.array([[5.0, np.nan], [5.0, 3.6], [np.nan, np.nan], [1.2, np.nan]])
    share = np.array([[1.0, 0.0], [0.5, 0.5], [1.0, 0.0], [1.0, 0.0]])
    got = so._loglik(counts, depth, share, 2.0, 50.0)
    edges = np.arange(N_BINS + 1) * so.BIN_S
    from scipy.special import ndtr
    want = []
    for k in range(4):
        lam = np.full(N_BINS, 50.0 / N_BINS)
        for j in range(2):
            if np.isfinite(depth[k, j]):
                tau = 2 * depth[k, j] / so.C
                lam += 2.0 * share[k, j] * np.diff(ndtr((edges - tau) / so.SIGMA_S))
        want.append(poisson.logpmf(counts[k], lam).sum())
    const = [poisson.logpmf(counts[k], 1.0).sum() + N_BINS for k in range(4)]
    np.testing.assert_allclose(got, np.array(want) - np.array(const), rtol=1e-10,
                               atol=1e-8)


def test_the_oracle_places_edges_its_photons_decide():
    """With 10 signal photons a pixel against 2 of background, every pixel beside the
    turned scene's box edges is placed right; at 2 against 50 some pixels beside them
    are not, and only pixels the edges' moves reach can be."""
    names = ["box_r0", "box_c0"]
    prepared = so._configs(30.0, names=names)
    report, wrong, truth = so.oracle(30.0, 1, 10.0, 2.0, prepared)
    assert not wrong.any()
    wrongs = 0
    for seed in (1, 2, 3):
        report, wrong, truth = so.oracle(30.0, seed, 2.0, 50.0, prepared)
        wrongs += wrong.sum()
        touched = np.zeros(truth.surface.shape, bool)
        for idx, *_ in prepared[1].values():
            touched.ravel()[idx] = True
        assert not (wrong & ~touched).any()
    assert wrongs >= 1
    # and the pixels it does not touch report the truth (the nearer surface where two)
    d = np.fmin(truth.depth[..., 0], truth.depth[..., 1])
    keep = ~touched & np.isfinite(d)
    np.testing.assert_array_equal(report[keep], d[keep])


def test_the_oracle_is_reproducible():
    """The same seed, the same frame and the same answer."""
    prepared = so._configs(0.0, names=["floor_r"])
    a = so.oracle(0.0, 7, 2.0, 50.0, prepared)
    b = so.oracle(0.0, 7, 2.0, 50.0, prepared)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    np.testing.assert_array_equal(histograms(a[2], 2.0, 50.0, 7),
                                  histograms(b[2], 2.0, 50.0, 7))
