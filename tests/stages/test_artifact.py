import numpy as np
import pytest

from schemas import CalibrationError
from stages.artifact import ArtifactBounds, estimate_bounds


def hist_with(block, artifacts, rng, rate=20.0, art_rate=0.5):
    h = np.zeros((1, 256), np.int64)
    h[0, block[0]:block[1] + 1] = rng.poisson(rate, block[1] - block[0] + 1)
    if artifacts:
        h[0, artifacts[0]:artifacts[1] + 1] += rng.poisson(art_rate,
                                                          artifacts[1] - artifacts[0] + 1)
    return h


@pytest.mark.parametrize("block", [(24, 150), (1, 255), (0, 100), (60, 61)])
def test_clean_block_is_found_exactly(block, rng):
    b = estimate_bounds(hist_with(block, None, rng))
    assert (int(b.n_min[0]), int(b.n_max[0])) == block


@pytest.mark.parametrize("art_rate", [0.05, 0.5, 2.0])
def test_sparse_artifacts_above_nmax_are_excluded(art_rate, rng):
    h = hist_with((24, 150), (151, 255), rng, art_rate=art_rate)
    b = estimate_bounds(h)
    assert (int(b.n_min[0]), int(b.n_max[0])) == (24, 150)


def test_missing_codes_inside_the_block_are_kept(rng):
    h = hist_with((30, 130), (140, 250), rng, rate=3.0, art_rate=0.05)
    h[0, 60:63] = 0  # three missing codes at low statistics
    b = estimate_bounds(h)
    assert (int(b.n_min[0]), int(b.n_max[0])) == (30, 130)


def test_empty_tdc_gets_full_range_and_others_unaffected(rng):
    h = np.vstack([hist_with((24, 150), (160, 200), rng), np.zeros((1, 256), np.int64)])
    b = estimate_bounds(h)
    assert b.n_min.tolist() == [24, 0] and b.n_max.tolist() == [150, 255]


def test_one_count():
    h = np.zeros((1, 256), np.int64)
    h[0, 77] = 1
    b = estimate_bounds(h)
    assert (int(b.n_min[0]), int(b.n_max[0])) == (77, 77)


def test_invalid_bounds_are_refused():
    with pytest.raises(CalibrationError, match="invalid"):
        ArtifactBounds(np.array([10]), np.array([5]))
    with pytest.raises(ValueError, match=r"must be \(n_tdc, 256\)"):
        estimate_bounds(np.zeros((2, 100)))
