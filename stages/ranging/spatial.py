"""Ranging with the neighbours: where a pixel sees a handful of signal photons in strong
background, the pixels around it mostly lie on the same surface (Rapp & Goyal 2017's
censoring of background photons by neighbourhood; Lindell 2018's benchmark).

On an image of histograms (rows, cols, bins) on one time axis, at a constant cost per
pixel (every step below is a sum over a fixed window or a prefix-sum difference):

1. Candidates. The histograms are summed over a (2k+1)^2 window around each pixel and over
   +-1.2 sigma of the pulse in time; the largest excess over the window's background and the
   next one at least 4 sigma away are the candidate surfaces, each kept where the window's
   count is a detection at ``p_fa`` over the bins (the exact Poisson tail, the union bound).
   A background estimated from no count (a dark frame) is half a count over the bins.
   And the pixel's own strongest box, where it is a detection against its own
   background at ``p_fa`` over the frame's bins and pixels and no window candidate is
   near it: a lone return of a few photons that no window sees (2d ranges it).
2. Censoring and a local plane. For each candidate, three mean-shift steps fit a plane
   t = t0 + a dr + b dc to the background-subtracted photons of the neighbours that fall
   within +-2.5 sigma of the plane (a weighted least squares on prefix sums: every
   neighbour's counts, sum of times and of squares in the window). Photons of another
   surface fall outside the window and are censored: a depth edge stays an edge, and
   a slanted plane is not bent. The pixel itself is left out of the fit, so its own
   photons can test it (3).
   2b. A depth step inside the window, too small for the censoring (two surfaces a few
   pulse widths apart: the plane becomes a ramp between them). Each of the window's 8
   halves through the pixel along its rows, columns and diagonals (16, at 8 directions,
   where the neighbours hold ``STEP_FINE`` net photons each on average) fits its own plane
   from the same sums; the one whose photons spread least about it (Kuwahara's choice, in
   Katkovnik's directional windows) is compared with the window's. Where the two agree,
   their squared difference less its noise variance is added to t0's variance (a bias the
   plane may carry); where they differ by more than ``STEP_Z`` sds and the window's
   quadratic misfits its neighbours, or two planes (the half's, the rest's) fit them better
   (a curved surface passes), the half, re-centred on its own plane, gives t0 and its
   variance. Both from the neighbours only: 3's test holds. Where it does not refit,
   the largest such bias of any of the 8 halves that differs by ``STEP_ANY`` sds is
   added to the reported sigma of a detected return (:func:`_step_lean`: beside a step
   of 1-2 pulse sigmas the least spread half is often one across it).
   2c. After 3's decision, the photons of a pixel they detect (their mean, re-centred on
   them) are a second estimate of its time: where they lie more than ``OWN_Z`` sds from t0,
   their squared difference less its noise is a bias t0 may carry (within half a pixel of a
   step at an angle no half follows, every half holds both surfaces), and the larger of it
   and 2b's enters t0's variance. t0 stays the plane's.
   2d. Unless the neighbours do not hold the surface (their counts about the plane are no
   detection at ``p_fa``, about the plane or about the pixel's own time: a lone point,
   a retroreflector, a post's tip): then the plane is their background's, and the
   pixel's own photons' mean gives t0, their spread its variance; and the pixel is
   detected where its own photons there pass ``p_fa`` over the places the mean could
   take (the union bound).
3. Decision, per pixel and candidate. The pixel's own counts in +-2 sigma of t0 against
   its background alone: a window fixed by the neighbours, so no look-elsewhere, and
   background alone passes with probability at most ``p_fa`` (the exact Poisson tail).
   Or, the surface surrounds the pixel: each of the four (k+1)^2 windows that have the
   pixel in a corner holds a detection at t0 (each at ``p_fa``), unless the photons of
   the pixel, or of the 3 x 3 around it, refuse it (fewer than the best corner window's
   signal a pixel leaves at ``p_fa``). A pixel beside an object, in empty sky, has a
   quarter of windows that see only sky, and so no surface unless its own photons say
   so; one in a wedge of sky narrower than a right angle has none, and only the photons
   around it can refuse it. A candidate later than one the window detects must also rise:
   the neighbours' counts within +-``RISE`` sigmas of its plane above their counts
   before it (:func:`_rises`, at ``p_fa`` over the bins between the two), or it is a
   tail of the earlier return (a SPAD's response decays over 0.1-1 ns; the model's pulse
   is Gaussian), not a surface. Given the response measured (``response``,
   :func:`measure_response` on a zero-distance frame), it must also stand above the
   background plus the earlier returns' expected response there
   (:func:`_above_response`: a delay that peaks, a bump that rises, is expected).
   3b. Which candidate an undetected pixel reports (:func:`_relabel`): from where a
   graph cut over the frame's planes puts it (:mod:`stages.ranging.planecut`: the
   labelling of least likelihood plus boundary length, isotropic), a few ICM sweeps
   of a Potts MRF over its candidates and its 8 nearest's planes carried over, by the
   pixel's own Poisson likelihood, how many of its 8 nearest lie on each, and how many
   of the 6 pixels of its best row, column or diagonal (a straight boundary); then block
   moves, which shift a boundary's whole run by one pixel where the sum over the run
   and its neighbourhood rises (a local minimiser moves one pixel at a time, and the
   line prior holds each pixel of a straight boundary where it is); last, edges
   (:func:`_edges`): a pixel beside a boundary goes to the side of the straight edge
   that the photons of the 11 x 11 window around it place (every line at any angle,
   weighed by their likelihood), or, near a corner, of the windows beside it; then of
   the straight edge its whole run's photons place (:mod:`stages.ranging.edgelines`),
   where a detection beside the line whose own photons and the line's disagree is
   withdrawn (the pixel labelled, its sigma keeping the chance it was right). And a
   detection no neighbour holds (none of its 8 nearest lies on its plane, detects it
   or sees its photons) whose own photons are no detection at the frame's level
   (``p_fa`` over the frame's pixels, as step 1's lone candidates) is weighed as an
   undetected pixel's label is; where another plane scores higher, that plane is the
   pixel's first return, its sigma keeping the chance the detection's surface is the
   pixel's, and the detection a further return (:func:`_islands`).
   A surface only the corner windows detect (the pixel's own photons do not) does not
   hold the pixel there: the pixel is labelled as an undetected one, and the detection
   stands only where the label lies on its surface (the pixel's other corner windows'
   surfaces then stand too, as further returns); elsewhere it is withdrawn and the
   label reported. A plane fitted across two surfaces (a pane above a slanted floor)
   passes the corner windows and misses the pixel by many pulse widths.
4. sigma: the photons' spread about the plane over their number, through the fit's
   design (its (0, 0) element), with the background left in the window, or the fit's
   sandwich variance, the larger; times Huber's factor for a window centred on its own
   estimate; plus the ridge's pull on t0 where the neighbours are one-sided. Both
   variances also with the fit's information from the neighbours' signed net counts
   (a neighbour without signal has none), the larger kept. Given each pixel's time
   axis's own error variance (a chip's calibration, ``cal_var_s2``), the model's
   variance gains the sum over the neighbours of their squared weight on t0 times it.
   An undetected pixel's reported surface (3b) has instead the spread of the planes on
   it that the relabelling weighed, each by its posterior (:func:`_label_sigma`).
5. A surface that is not a plane (:func:`_curvature`): a detected return's t0 corrected
   by the curvature its window averages, and an undetected one's from the detected
   returns around it, where a quadratic over them says so; where it fits but does not
   say so, its squared estimate less its variance enters the detected return's sigma.
6. An undetected return on a surface that is not the pixel's (:func:`_off_surface`):
   where the pixel's own photons make it ``OFF_P`` likely or more that it lies on none
   of it (a mixture over the pixels around it: on the surface, on another of the
   frame's planes, or elsewhere; its photons at the reported time and at each plane),
   or its photons and those of the undetected returns of its 3 x 3 on the same surface
   together do (:func:`_off_pool`), its sigma reaches the farthest surface reported
   within ``OFF_K`` pixels, among its own candidates or among the frame's planes where
   its photons are.

Up to ``max_returns`` (2) surfaces a pixel, the strongest first (detected before not),
but an island's label (3b) before its detection.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import product
from typing import NamedTuple

import numpy as np
from scipy import ndimage
from scipy.special import erf, expit, logit, pdtr

from stages.ranging import edgelines, planecut
from stages.ranging._numba import numba
from stages.ranging.detection import (
    poisson_tail,
    profile_keep,
    profile_passes,
    profile_per_bin,
    rise_p,
)

WINDOW = 3      # k: the window is (2k + 1)^2 pixels
CURVE_R = 4     # the curvature's quadratic: over the (2 CURVE_R + 1)^2 around a pixel
CURVE_Z = 3.0   # and it corrects t0 where it is this many of its sds from 0
CURVE_MIN = 12  # of that many detected returns on the pixel's surface at least
CURVE_LEAN = True  # and where it does not correct, its bias less its noise in the sigma
UNDET_TOL = 6.0  # an undetected pixel's surface: its 3 x 3's detected returns this many
                 # pulse sigmas from its time (0: its time stays the plane's)
NEAR_OTHER = 10.0  # and not where a detected return off that surface is within this many
CHI_MAX = 2.0      # or the quadratic misses its returns by more (reduced chi-square)
STEP_ANY = 3.0   # and any half this many sds off gives the detected return's sigma its bias
STEP_Z = 3.0     # a half of the window whose plane is this many sds off the window's (0: off)
STEP_LOF = 3.0   # where the window's quadratic misfits by this many sds of its chi-square
STEP_TWO = 5.0   # or two planes (the half's, the rest's) fit by this much chi-square better
STEP_MIN = 12    # pixels in the image a half holds at least, its window twice as many
STEP_ITER = 3    # takes the pixel, its plane re-centred this many times
STEP_FINE = 3.0  # net photons a neighbour (the window's positive net counts over its
                 # neighbours in the image) from which 2b tries 16 halves, at 8 directions
                 # (below it, and at 0, the 8 along the rows, columns and diagonals)
OWN_Z = 2.0      # 2c: a pixel's own photons this many sds off its plane (0: off)
OWN_MIN = 3      # counts the pixel needs in its own window, about its photons' mean
WIDTH_FIT = 2.5  # the plane fit's window, +- sigmas of the pulse
WIDTH_TEST = 2.0  # the pixel's own test window
BOXES = (1.2, 4.0, 10.0)  # the candidates' time boxes, +- sigmas of the pulse
CANDIDATES = 4   # surfaces searched for in a window (a pixel keeps up to max_returns)
PRIOR = 0.7      # the relabelling's weight (nats) of each of the 8 nearest that agree
LINE = 0.4       # and of each pixel of its best straight line through the pixel that agrees
LINE_L = 3       # that line's reach each side (pixels)
DIAG = 0.5       # a diagonal line's weight against a row's or a column's
SWEEPS = 5       # its ICM sweeps (3: 0.69 % > 10 cm off at (2, 50), 8: as 5)
BLOCK_ROUNDS = 1  # then block moves (a boundary's run shifted by a pixel), each direction
BLOCK_PHASES = 4  # in 4 passes of every 4th column (row)
EDGE_LINES = True  # the edges' last step: each straight boundary as one line (edgelines.py)
EDGE_SIGMA = True   # the lines' posteriors in an undetected pixel's sigma (_line_var)
EDGE_SIGMA_P = 0.05  # where the other plane holds at least this share of the posterior
EDGE_DOUBT = True  # and there a detection the line and its own photons refute withdrawn
LINE_SKY = True    # the lines leave out the pixels that see no surface (_no_surface)
ISLAND = True      # a detection no neighbour holds decided as a label (_islands)
LINE_PASSES = 2    # the lines' step again on the labels its moves corrected (runs that a
#                    wrong label at an end cut short or tilted are found whole): the last
#                    pass doubts detections; every pass's posteriors give sigma
NONE_K = 2         # no surface: an undetected pixel whose (2 NONE_K + 1)^2 around it holds,
NONE_P = 0.023     # summed, no detection at this p (2 sds' one tail) about each plane's time
NONE_OPEN = True   # and a 3 x 3 of such pixels covers (a binary opening)
LONE = True        # 2d: a surface the neighbours do not hold ranged by the pixel's photons
RESPONSE_CHECK = 0.05  # 3: a measured response holds before a later return at this level
RISE = 1.5         # 3: a return after a detected one: its neighbours' counts in +- this many
#                    sigmas rise over theirs before it (0: off; a response's tail decays)
OWN_CAND = True    # 1: the pixel's own strongest box a candidate where the windows' miss it
PROFILE_BLOCK = 32  # the background's time profile: its blocks (bins)
PROFILE_P = 1e-4    # and the chi-square test's p below which the frame is not flat
MASK_K = WINDOW   # over the window's neighbourhood (3 x 3: the scene's returns leaked and the
                  # flat frames of Lindell's grid came out not flat)
SIGNAL_Z = 3.1      # a block whose neighbourhood's count stands this many sd above: a return's
BLOCK_PAIR = 1.5  # the priors' weight in a block's sum (seed 1: 1.5-3 alike, 1 and 0.5 worse)
OFF_P = 0.2      # 6: an undetected first return whose own photons make it this likely
                 # that it is not on the surface it reports (0: off)
OFF_K = 4        # the mixture over the (2 OFF_K + 1)^2 around the pixel, and the reach of
                 # the surfaces reported there
OFF_FLOOR = 0.25  # such a return's variance gains at least this share of the farthest's
                  # squared distance (2 sigma then reaches it)
OFF_POOL = 1     # 6's test also over the (2 OFF_POOL + 1)^2 around the pixel (0: off): its
OFF_SAME = 4.0   # undetected returns within this many pulse sigmas of its time, together
OFF_ITER = 8     # the mixture's EM steps
OFF_OWN_MIN = 2  # a candidate the window does not detect is a surface the pixel may be on
                 # where this many of the pixel's own photons lie at it (0: every one)
OFF_PLANES = True  # 6 also reads the frame's planes (3b's cut): a surface the pixel may be on
                   # where OFF_OWN_MIN of its own photons lie at it (D)
OFF_MIX = True     # and, off its surface, a return is on one of them (its own photons there
                   # say which) or elsewhere, the share learnt (_off_planes; False: elsewhere)


def _mshift_factor(c: float) -> float:
    from scipy.stats import norm

    p = 1 - 2 * norm.sf(c)
    return float((p / (p - 2 * c * norm.pdf(c))) ** 2)


MSHIFT = _mshift_factor(WIDTH_FIT)


def QUADRANTS(dr, dc):  # noqa: N802
    """The four (k+1)^2 windows with the pixel in a corner."""
    return [(dr * a >= 0) & (dc * b >= 0) for a in (1, -1) for b in (1, -1)]


@dataclass(frozen=True)
class SpatialEstimate:
    """Per pixel and return (rows, cols, max_returns): ``t_s`` (NaN: no candidate),
    ``sigma_s``, ``signal_counts`` (the neighbourhood's signal per pixel, background
    subtracted), ``background_per_bin``, ``detected``, and how (``own``: the pixel's own
    photons; ``surrounded``: the four corner windows)."""

    t_s: np.ndarray
    sigma_s: np.ndarray
    signal_counts: np.ndarray
    background_per_bin: np.ndarray
    detected: np.ndarray
    own: np.ndarray
    surrounded: np.ndarray


def _box(a: np.ndarray, k: int, dtype=np.float64) -> np.ndarray:
    """Sums over the (2k+1)^2 window (clipped at the image's edges) along axes 0 and 1,
    in ``dtype``: shifted adds along each axis (numpy's prefix sums along the image's
    axes, not the array's last, cost 2-5x as much on a frame). float64 values that float32
    holds exactly (photon counts) are added as float32: the same sums, a third of the
    time of adding float64 into float32."""
    rows = np.array(a, dtype)
    if rows.dtype != a.dtype and np.array_equal(rows, a):
        a = rows.copy()
    for d in range(1, k + 1):
        rows[d:] += a[:-d]
        rows[:-d] += a[d:]
    out = rows.copy()
    for d in range(1, k + 1):
        out[:, d:] += rows[:, :-d]
        out[:, :-d] += rows[:, d:]
    return out


def _cumbins(a: np.ndarray, dtype=np.float64) -> np.ndarray:
    """Prefix sums along the bins with a leading 0."""
    out = np.empty(a.shape[:-1] + (a.shape[-1] + 1,), dtype)
    out[..., 0] = 0
    np.cumsum(a, axis=-1, out=out[..., 1:])
    return out


def _span(a, z, prof):
    """The background's share of bins [a, z): z - a for a flat one, else its profile's
    sum over them (``prof``: :func:`background_profile`'s)."""
    return z - a if prof is None else prof[1][z] - prof[1][a]


def _rate(count, bins, all_bins):
    """A background's rate a bin: ``count`` over ``bins``, at least half a count over
    ``all_bins`` (the histogram's bins its count could have fallen in: the rate's mean
    under Jeffreys' prior where it saw none). No count in a dark frame is no proof of no
    background, and a rate of 0 makes a single photon a detection at any p_fa (an
    outside probe's dark frames, 0.02 photons a pixel: up to 40 false surfaces a frame
    at p_fa 1e-6). Half a count added to every count instead moved ~90 detections in 25
    frames of (2, 50) beside their threshold, and the turned scene's labels with them
    (267 -> 293 pixels > 10 cm off); half a count over ``bins`` alone, on a 64-bin
    histogram whose box leaves one bin outside, made 0.5 a bin of a 0.05 background."""
    return np.maximum(count / np.maximum(bins, 1.0), 0.5 / all_bins)


def background_profile(counts: np.ndarray, block: int = PROFILE_BLOCK,
                       p: float = PROFILE_P) -> tuple | None:
    """The background's time profile over the frame, or None where the frame's background
    is flat within its noise. Every estimate and test of the estimator takes a pixel's
    background as its rate times this profile; a flat one (None) is what it assumed
    before. A background that is not flat in time (pile-up of ambient light in counts not
    corrected for it, an afterpulsing tail, a gate's edge) with a flat model makes the
    bins where it is above its mean look like returns: on empty frames whose background
    falls as e^-3t over the window, at 50 photons a pixel, 0.93 of the pixels were
    detected at p_fa 1e-3 (benchmarks/spatial_background.py).

    The frame's counts in blocks of ``block`` bins give the profile: every pixel's kept
    counts over the counts its own rate a bin would put in each block (three passes,
    from the profile of all counts). A block is left out of a pixel, with the blocks
    beside it, where its 7 x 7 neighbourhood's count is beyond that neighbourhood's
    background's tail at ``SIGNAL_P`` (the returns; a threshold, not the largest excess:
    picking the largest left out the rare counts of the faint blocks, and a falling
    profile came out low at its end). A chi-square test of the kept counts against
    each pixel's flat rate decides: flat at p >= ``p`` (None; every frame of Lindell's
    grid, seeds 1-5). The profile is the same for every pixel (their rates differ); it
    follows changes slower than a block (2.5 ns at 80 ps bins),
    not a faster one. Returns (s, S0, S1, S2): s the profile a bin, mean 1; S0, S1, S2
    the prefix sums (length bins + 1) of s, s (j + 0.5) and s (j + 0.5)^2."""
    from scipy.stats import chi2

    h, w, n = counts.shape
    nb = n // block
    if nb < 6:
        return None
    edges = np.arange(nb + 1) * block
    edges[-1] = n                                    # the last block takes the rest
    width = np.diff(edges).astype(np.float64)
    blk = np.add.reduceat(counts, edges[:-1], axis=-1)        # (h, w, nb)
    # the returns' blocks, by the 7 x 7 neighbourhood's counts; the profile from the
    # pixel's own
    keep = profile_keep(_box(blk, MASK_K), np.broadcast_to(width, blk.shape), SIGNAL_Z)
    kept = np.where(keep, blk, 0.0)
    prof = profile_passes(kept, keep * width)
    # the test against each pixel's flat rate over its kept blocks
    rate0 = kept.sum(-1) / np.maximum((keep * width).sum(-1), 1e-300)
    expect = (keep * rate0[..., None]).sum((0, 1)) * width
    obs = kept.sum((0, 1))
    use = expect > 0
    if use.sum() < 4:
        return None
    x2 = float((((obs - expect) ** 2)[use] / expect[use]).sum())
    if chi2.sf(x2, use.sum() - 1) >= p:
        return None
    tj = np.arange(n) + 0.5
    sj = profile_per_bin(prof, (edges[:-1] + edges[1:]) / 2.0, tj)

    def cum(x):
        return np.concatenate([[0.0], np.cumsum(x)])

    return sj, cum(sj), cum(sj * tj), cum(sj * tj * tj)


def spatial(counts: np.ndarray, bin_s: float, sigma_s: float, p_fa: float = 1e-3,
            window: int = WINDOW, max_returns: int = 2, t0_s: float = 0.0,
            threads: int = 1, compiled: bool | None = None,
            cal_var_s2: np.ndarray | None = None,
            response: SpatialResponse | None = None) -> SpatialEstimate:
    """Range an image of histograms with its neighbours (module docstring).

    ``counts`` (rows, cols, bins) photon counts (no pile-up: a photon-counting histogram
    or one already corrected), bin j spanning ``t0_s + [j, j + 1) bin_s``; ``sigma_s``
    the pulse's (instrument response's) sigma. ``threads`` > 1 ranges bands of rows at
    once (numpy releases the GIL), each with ``2 window + 2`` rows of its neighbours', then
    relabels the whole image, so the result is the same as in one piece (tested).
    ``compiled``: step 1's search, the plane fits' window sums, the relabelling's prior
    and the edges' windows (3b) by numba (default where it is installed) or numpy (the
    same result, tested). ``cal_var_s2``
    (rows, cols): each pixel's time axis's own error variance (s^2; a chip's
    calibration, fixed a pixel, independent between pixels), which the estimate carries
    as the fit weighs its neighbours: the sigma gains the sum over the neighbours of
    their squared weight on t0 times it (4). ``response``: the instrument's measured
    response behind a return (:func:`measure_response`, on a zero-distance frame): a
    return after a detected one must then stand above the background plus the earlier
    returns' expected response there (step 3, in place of the rise test: any shape, a
    peaked delay too).
    """
    compiled = (numba is not None) if compiled is None else bool(compiled) and numba is not None
    counts = np.asarray(counts, np.float64)
    _check(counts, bin_s, sigma_s, p_fa, window, max_returns)
    if cal_var_s2 is not None:
        cal_var_s2 = np.asarray(cal_var_s2, np.float64)
        if cal_var_s2.shape != counts.shape[:2] or not np.all(cal_var_s2 >= 0):
            raise ValueError(f"cal_var_s2 must be (rows, cols) = {counts.shape[:2]}, finite "
                             f"and >= 0, found {cal_var_s2.shape}")
    if response is not None:
        if not isinstance(response, SpatialResponse):
            raise TypeError(f"response must be a SpatialResponse (measure_response), found "
                            f"{type(response).__name__}")
        if not np.isclose(response.bin_s, bin_s, rtol=1e-9, atol=0.0):
            raise ValueError(f"the response was measured on bins of {response.bin_s:g} s, "
                             f"the frame's are {bin_s:g} s")
    h = counts.shape[0]
    prof = background_profile(counts)
    bands = min(max(1, int(threads)), max(1, h // (4 * window + 4)))
    if bands == 1:
        return _finish(_spatial(counts, bin_s, sigma_s, p_fa, window, max_returns, t0_s,
                                compiled, cal_var_s2, prof, response),
                       max_returns, bin_s, sigma_s / bin_s, t0_s, prof, compiled, threads,
                       p_fa)
    from concurrent.futures import ThreadPoolExecutor

    edges = np.linspace(0, h, bands + 1).astype(int)
    # a pixel's fit reads its neighbours' (window) background rates, each over the 3 x 3
    # around it outside the window's (window) strongest candidate
    halo = 2 * window + 2
    parts = [(max(a - halo, 0), a, b, min(b + halo, h))
             for a, b in zip(edges[:-1], edges[1:], strict=True)]
    with ThreadPoolExecutor(bands) as ex:
        got = list(ex.map(lambda p: _spatial(
            counts[p[0]:p[3]], bin_s, sigma_s, p_fa, window, max_returns, t0_s, compiled,
            None if cal_var_s2 is None else cal_var_s2[p[0]:p[3]], prof, response), parts))
    fields = tuple(np.concatenate([e[i][a - lo:b - lo]
                                   for e, (lo, a, b, _) in zip(got, parts, strict=True)])
                   for i in range(len(got[0])))
    return _finish(fields, max_returns, bin_s, sigma_s / bin_s, t0_s, prof, compiled, threads,
                   p_fa)


def _check(counts, bin_s, sigma_s, p_fa, window, max_returns) -> None:
    if counts.ndim != 3 or min(counts.shape) < 1 or counts.shape[2] < 3:
        raise ValueError(f"counts must be (rows, cols, bins >= 3), found {counts.shape}")
    if counts.shape[0] * counts.shape[1] < 2:
        raise ValueError("spatial ranging needs an image of at least 2 pixels (each pixel "
                         f"is ranged by its neighbours), found {counts.shape[:2]}")
    if not np.all(np.isfinite(counts)) or counts.min() < 0:
        raise ValueError("counts must be finite and >= 0")
    for name, v in (("bin_s", bin_s), ("sigma_s", sigma_s)):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be positive and finite, found {v}")
    if not 0 < p_fa < 1:
        raise ValueError(f"p_fa must be in (0, 1), found {p_fa}")
    if not (1 <= window <= 16 and 1 <= max_returns <= 4):
        raise ValueError(f"window must be 1..16 and max_returns 1..4, found {window}, "
                         f"{max_returns}")


def _boxed(A: np.ndarray, k: int) -> np.ndarray:
    """Counts in bins [j - k, j + k] (clipped) for every bin j, from the prefix sums
    ``A`` (h, w, n + 1): A[min(j + k + 1, n)] - A[max(j - k, 0)], by slices."""
    h, w, n = A.shape[0], A.shape[1], A.shape[2] - 1
    if 2 * k + 1 > n:
        p = np.pad(A, ((0, 0), (0, 0), (k, k)), mode="edge")
        return p[..., 2 * k + 1:2 * k + 1 + n] - p[..., :n]
    out = np.empty((h, w, n), A.dtype)
    np.subtract(A[..., 2 * k + 1:], A[..., :n - 2 * k], out=out[..., k:n - k])
    np.subtract(A[..., k + 1:2 * k + 1], A[..., :1], out=out[..., :k])
    np.subtract(A[..., n:], A[..., n - 2 * k:n - k], out=out[..., n - k:])
    return out


def _box_argmax(A: np.ndarray, k: int, compiled: bool) -> tuple:
    """Each pixel's strongest box of +- ``k`` bins (:func:`_boxed`): its centre bin (the
    first on a tie) and its counts, in ``A``'s dtype; by numba where ``compiled`` (the
    same result, tested)."""
    if compiled:
        return _box_argmax_numba(A, k)
    boxed = _boxed(A, k)
    c = np.argmax(boxed, axis=-1)
    return c, np.take_along_axis(boxed, c[..., None], -1)[..., 0]


def _search(PA, bgA, halves, sb, nc, prof, compiled) -> tuple:
    """Step 1's search: each bin's excess over the window's background (``bgA`` a bin,
    spread over the bins by ``prof``) in sds, float32, for a box of each of ``halves``
    (+- bins) with its best kept, then ``nc`` candidates block by block (blocks of
    ``int(sb)`` bins), each the strongest block left, and the blocks within its box and
    4 sigma of it left out from then on. Returns (h, w, nc) each: the candidates' bins,
    their boxes' half widths (bins, float) and whether a box was left to take (not
    every block left out). By numba where ``compiled``: the same float32 operations in
    the same order, one pixel at a time without the (h, w, n) temporaries (the same
    result, tested)."""
    h, w, n = PA.shape[0], PA.shape[1], PA.shape[2] - 1
    B = max(1, int(sb))
    hv = np.array(halves, np.int64)
    if compiled:
        S0 = np.zeros(1) if prof is None else np.asarray(prof[1], np.float64)
        cand, which, live = _search_numba(PA, np.asarray(bgA, np.float64), hv, float(sb), B,
                                          nc, prof is None, S0)
        return cand, hv[which].astype(np.float64), live
    Z = np.full((h, w, n), -np.inf, np.float32)
    which = np.zeros((h, w, n), np.int8)
    for i, kb in enumerate(halves):
        # the box's excess over its background in sds: in place, the box's full width
        # inside the bins, its clipped ends apart
        z = _boxed(PA, kb).astype(np.float32, copy=False)
        if prof is not None:  # the background's profile over each bin's box
            jb = np.arange(n)
            b = bgA[..., None].astype(np.float32) * _span(
                np.maximum(jb - kb, 0), np.minimum(jb + kb + 1, n), prof).astype(np.float32)
            z -= b
            z /= np.sqrt(b + np.float32(1.0))
        else:
            m = slice(kb, n - kb) if n > 2 * kb else slice(0, 0)
            b = (bgA * (2 * kb + 1)).astype(np.float32)[..., None]
            z[..., m] -= b
            z[..., m] /= np.sqrt(b + np.float32(1.0))
            for e_ in (slice(0, min(kb, n)), slice(max(n - kb, min(kb, n)), n)):
                j_ = np.arange(n)[e_]
                nb = np.minimum(j_ + kb + 1, n) - np.maximum(j_ - kb, 0)
                b = (bgA[..., None] * nb).astype(np.float32)
                z[..., e_] = (z[..., e_] - b) / np.sqrt(b + np.float32(1.0))
        np.copyto(which, np.int8(i), where=z > Z)
        np.maximum(Z, z, out=Z)
    # the best of every block of bins (the first on a tie, as a running maximum: numpy's
    # argmax over a last axis of 2 took 6 % of the frame)
    nblk = -(-n // B)
    Zp = np.pad(Z, ((0, 0), (0, 0), (0, nblk * B - n)), constant_values=-np.inf)
    Zp = Zp.reshape(h, w, nblk, B)
    Zb = Zp[..., 0].copy()
    inb = np.zeros((h, w, nblk), np.int64)
    for i in range(1, B):
        np.copyto(inb, i, where=Zp[..., i] > Zb)
        np.maximum(Zb, Zp[..., i], out=Zb)
    cand = np.zeros((h, w, nc), np.int64)
    half = np.zeros((h, w, nc))
    live = np.zeros((h, w, nc), bool)
    blkB = np.arange(nblk) * B
    for r in range(nc):
        k = np.argmax(Zb, axis=-1)
        c = k * B + np.take_along_axis(inb, k[..., None], -1)[..., 0]
        kb = hv[np.take_along_axis(which, c[..., None], -1)[..., 0]]
        cand[..., r], half[..., r] = c, kb
        live[..., r] = np.take_along_axis(Zb, k[..., None], -1)[..., 0] > -np.inf
        # |blk B - c| <= kb + 4 sb + B, in integers: the bound's floor
        reach = np.floor(kb + 4 * sb + B).astype(np.int64)[..., None]
        near = (blkB >= (c[..., None] - reach)) & (blkB <= (c[..., None] + reach))
        Zb = np.where(near, -np.inf, Zb)
    return cand, half, live


if numba is not None:
    @numba.njit(cache=True, nogil=True)
    def _box_argmax_numba(A, k):
        """:func:`_box_argmax` a pixel at a time (equal results)."""
        h, w, n1 = A.shape
        n = n1 - 1
        idx = np.zeros((h, w), np.int64)
        val = np.empty((h, w), A.dtype)
        for i in range(h):
            for j in range(w):
                best = A[i, j, min(k + 1, n)] - A[i, j, 0]
                bi = 0
                for t in range(1, n):
                    v = A[i, j, min(t + k + 1, n)] - A[i, j, max(t - k, 0)]
                    if v > best:
                        best = v
                        bi = t
                idx[i, j] = bi
                val[i, j] = best
        return idx, val

    @numba.njit(cache=True, nogil=True)
    def _search_numba(PA, bgA, halves, sb, B, nc, flat, S0):
        """:func:`_search` a pixel at a time (its float32 operations in its order: equal
        results); returns the candidates' bins, their boxes' indices in ``halves`` and
        whether each was live."""
        h, w, n1 = PA.shape
        n = n1 - 1
        nblk = (n + B - 1) // B
        cand = np.zeros((h, w, nc), np.int64)
        hix = np.zeros((h, w, nc), np.int64)
        live = np.zeros((h, w, nc), np.bool_)
        Z = np.empty(n, np.float32)
        zb = np.empty(n, np.float32)
        which = np.empty(n, np.int64)
        Zb = np.empty(nblk, np.float32)
        inb = np.empty(nblk, np.int64)
        one = np.float32(1.0)
        ninf = np.float32(-np.inf)
        for i in range(h):
            for j in range(w):
                bg = bgA[i, j]
                bg32 = np.float32(bg)
                for t in range(n):
                    Z[t] = ninf
                    which[t] = 0
                for q in range(halves.size):
                    kb = halves[q]
                    # (a flat background's box inside the bins: one b and root a box)
                    bi_ = np.float32(bg * (2 * kb + 1))
                    si_ = np.sqrt(bi_ + one)
                    inner = min(kb, n)
                    if flat and n > 2 * kb:
                        for t in range(kb, n - kb):
                            zb[t] = (np.float32(PA[i, j, t + kb + 1] - PA[i, j, t - kb])
                                     - bi_) / si_
                        inner = n - kb
                    for t in range(n):
                        if flat and kb <= t < inner:
                            continue
                        lo = max(t - kb, 0)
                        hi = min(t + kb + 1, n)
                        x = np.float32(PA[i, j, hi] - PA[i, j, lo])
                        if flat:
                            b = np.float32(bg * (hi - lo))
                        else:
                            b = bg32 * np.float32(S0[hi] - S0[lo])
                        zb[t] = (x - b) / np.sqrt(b + one)
                    for t in range(n):
                        up = zb[t] > Z[t]
                        which[t] = q if up else which[t]
                        Z[t] = zb[t] if up else Z[t]
                for bk in range(nblk):
                    t0 = bk * B
                    best = Z[t0]
                    bi = 0
                    for s in range(1, B):
                        if t0 + s < n and Z[t0 + s] > best:
                            best = Z[t0 + s]
                            bi = s
                    Zb[bk] = best
                    inb[bk] = bi
                for r in range(nc):
                    kmax = 0
                    vb = Zb[0]
                    for bk in range(1, nblk):
                        if Zb[bk] > vb:
                            vb = Zb[bk]
                            kmax = bk
                    c = kmax * B + inb[kmax]
                    q = which[c]
                    cand[i, j, r] = c
                    hix[i, j, r] = q
                    live[i, j, r] = vb > ninf
                    reach = np.int64(np.floor(halves[q] + 4 * sb + B))
                    for bk in range(nblk):
                        if abs(bk * B - c) <= reach:
                            Zb[bk] = ninf
        return cand, hix, live


def _spatial(counts, bin_s, sigma_s, p_fa, window, max_returns, t0_s, compiled,
             cal_var=None, prof=None, response=None) -> tuple:
    """Steps 1-3 on a band of rows: per pixel and candidate, before the relabelling."""
    h, w, n = counts.shape
    sb = sigma_s / bin_s                     # the pulse's sigma in bins
    P0 = _cumbins(counts)                    # (h, w, n + 1)
    # -- 1. candidates from the window's histogram, in time boxes of three widths (a
    # slanted surface spreads the window's photons over more bins). (A 3 x 3 window's
    # best as a fifth candidate, for edge pixels whose surface is the 7 x 7 window's
    # minority, took a tenth of a point off the pixels > 10 cm off at (2, 50) for 50 %
    # more time: not kept.)
    def between(P, a, z):  # P[..., z] - P[..., a] for (h, w) indices
        return (np.take_along_axis(P, z[..., None], -1)
                - np.take_along_axis(P, a[..., None], -1))[..., 0]

    def candidates(k_win, boxes, nc):
        # (float32 where every window's total is an integer float32 holds exactly: the
        # search only, its sums as in float64; 30 % of the frame's time in float64)
        dt = np.float32 if counts.sum(-1).max() * (2 * k_win + 1) ** 2 < 2 ** 24 else np.float64
        PA = _cumbins(_box(counts, k_win, dt), dt)       # (h, w, n + 1)
        halves = [max(1, int(round(x * sb))) for x in boxes]

        # the window's background a bin: the mean without the strongest box's region
        # (at least half a count over the histogram: :func:`_rate`)
        c0, _ = _box_argmax(PA, halves[0], compiled)
        e = int(halves[-1] + 4 * sb)
        a0, z0 = np.clip(c0 - e, 0, n), np.clip(c0 + e + 1, 0, n)
        bgA = _rate(PA[..., n] - between(PA, a0, z0), n - _span(a0, z0, prof), n)
        cand, half, live = _search(PA, bgA, halves, sb, nc, prof, compiled)
        ok = np.zeros((h, w, nc), bool)
        for r in range(nc):
            c, kb = cand[..., r], half[..., r].astype(np.int64)
            a, z = np.clip(c - kb, 0, n), np.clip(c + kb + 1, 0, n)
            # the union bound over the bins and the box widths
            ok[..., r] = ((poisson_tail(between(PA, a, z), bgA * _span(a, z, prof))
                           <= p_fa / (n * len(halves))) & live[..., r])
        if OWN_CAND:
            # the pixel's own strongest box, where the window's candidates miss it: a lone
            # return of a few photons (a retroreflector at range) is no excess over the
            # window's 49 pixels of background, and no candidate; the pixel's own box
            # against its own background is a detection at p_fa over the frame's bins and
            # pixels (the union bound: a surface no neighbour sees needs a frame's
            # evidence; at p_fa over its own bins alone, ~4 pixels a frame of (2, 50)
            # took a false return first). It takes the last slot no window candidate
            # holds (2d ranges it)
            k0 = halves[0]
            c1, cnt = _box_argmax(P0, k0, compiled)
            a1, z1 = np.clip(c1 - k0, 0, n), np.clip(c1 + k0 + 1, 0, n)
            bpix = _rate(P0[..., n] - cnt, n - _span(a1, z1, prof), n)
            got = poisson_tail(cnt, bpix * _span(a1, z1, prof)) <= p_fa / (n * h * w)
            far = ~(ok & (np.abs(cand - c1[..., None]) <= (half + 4 * sb))).any(-1)
            free_slot = ~ok
            last = nc - 1 - np.argmax(free_slot[..., ::-1], axis=-1)
            put = got & far & free_slot.any(-1)
            ii, jj = np.nonzero(put)
            cand[ii, jj, last[ii, jj]] = c1[ii, jj]
            half[ii, jj, last[ii, jj]] = k0
            ok[ii, jj, last[ii, jj]] = True
        return cand, half, ok

    cand, cand_half, cand_ok = candidates(window, BOXES, max(CANDIDATES, max_returns))
    nc = cand.shape[-1]
    # the pixels' own background a bin, outside the strongest candidate: over 3 x 3
    e0 = (cand_half[..., 0] + 4 * sb).astype(np.int64)
    a0, z0 = np.clip(cand[..., 0] - e0, 0, n), np.clip(cand[..., 0] + e0 + 1, 0, n)
    out_cnt = P0[..., n] - between(P0, a0, z0)
    beta = _rate(_box(out_cnt, 1), _box((n - _span(a0, z0, prof)).astype(np.float64), 1),
                 _box(np.full((h, w), float(n)), 1))      # (:func:`_rate`, as bgA)
    j = np.arange(n)
    # -- 2. the plane fit for every candidate, at every pixel
    # counts, sums of bin-time and of its square, prefix-summed together: one gather a
    # neighbour and window edge
    tj = j + 0.5
    P = np.zeros((h, w, n + 1, 3))
    P[..., 1:, 0] = P0[..., 1:]
    np.cumsum(counts * tj, axis=-1, out=P[..., 1:, 1])
    np.cumsum(counts * (tj * tj), axis=-1, out=P[..., 1:, 2])
    P = P.reshape(h * w * (n + 1), 3)   # (gathered by one flat index: 3.6x a 2-D index)
    d = np.arange(-window, window + 1)
    dr, dc = (x.ravel() for x in np.meshgrid(d, d, indexing="ij"))
    centre = (dr == 0) & (dc == 0)
    dr, dc = dr[~centre], dc[~centre]                      # (m,) offsets, the pixel left out
    R = np.arange(h)[:, None, None] + dr[None, None, :]
    Cc = np.arange(w)[None, :, None] + dc[None, None, :]
    inside = (R >= 0) & (R < h) & (Cc >= 0) & (Cc < w)     # (h, w, m)
    on = inside.astype(np.float64)
    q = np.clip(R, 0, h - 1) * w + np.clip(Cc, 0, w - 1)   # flat neighbour index
    qn = q * (n + 1)                                       # its prefix sums' first row
    beta_q = beta.ravel()[q] * on
    cal_q = None if cal_var is None else (cal_var / bin_s ** 2).ravel()[q] * on  # bins^2
    X = np.stack([np.ones_like(dr), dr, dc]).astype(np.float64)  # (3, m)
    XX = (X[:, None, :] * X[None, :, :]).reshape(9, -1).T       # (m, 9)

    def gram(wq):  # sum over the neighbours of wq X X^T: (h, w, 3, 3), one matrix product
        return (wq @ XX).reshape(wq.shape[:-1] + (3, 3))
    shape = (h, w, nc)
    t_out, sig_out, sig_cnt = np.full(shape, np.nan), np.full(shape, np.inf), np.zeros(shape)
    own, surr, rank = np.zeros(shape, bool), np.zeros(shape, bool), np.zeros(shape)
    seen = np.zeros(shape, bool)   # the window detects the candidate (6: a surface near)
    t0_r = np.full(shape, np.nan)  # each candidate's t0 (bins)
    # per candidate, for the relabelling (3b): the plane's slopes (bins a pixel), the
    # pixel's own counts in its test window and their background
    slope = np.zeros(shape + (2,))
    bend = np.zeros(shape + (3,))
    lean = np.zeros(shape)   # 2b: any half's bias, for the detected returns' sigma (bins^2)
    mine_r, bw_r = np.zeros(shape), np.zeros(shape)

    # (the numba kernel's background tables: a flat background's are unused)
    tables = (True, np.zeros(1), np.zeros(1), np.zeros(1)) if prof is None else (False, *prof[1:])

    tails = None   # the earlier returns' expected response (a measured one), while set

    def window_sums(tq, half, narrow=True):
        """Counts, sums of bin-time and of its square in tq +- half (bins), background
        subtracted, for every neighbour; and the raw counts and background. Where a
        response is measured, what the earlier returns leave there (``tails``) is
        background too (:func:`_tail_sums`)."""
        if compiled:
            hb = np.ascontiguousarray(np.broadcast_to(half, tq.shape[:2] + (1,))[..., 0])
            got = _window_sums_numba(P, qn, on, beta_q, tq, hb, n, *tables)
        else:
            got = _window_sums_numpy(P, qn, on, beta_q, tq, half, n, prof)
        if tails is None or not narrow:
            return got
        T0, T1, T2 = (x * on for x in _tail_sums(tq, half, n, response, *tails, dr, dc))
        n0, s1, s2, raw, bsum = got
        return n0 - T0, s1 - T1, s2 - T2, raw, bsum + T0

    # 2b's halves of the window (16, m), and where each is tried: a half of fewer than
    # STEP_MIN pixels in the image, or in a window of fewer than twice that, is not (a
    # plane from a few pixels at a corner or on a small array, a 4 x 4 chip's, is too
    # loose to tell a step; the chip's calibrated captures lost 1-7 mm of RMSE to it)
    hm = _halves(dr, dc)
    whole_h = ((on @ hm.T) >= STEP_MIN) & (on.sum(-1) >= 2 * STEP_MIN)[..., None]
    for r in range(nc):
        t0 = cand[..., r] + 0.5                               # bins
        a_s = np.zeros((h, w))
        b_s = np.zeros((h, w))
        if response is not None and r:
            # the earlier detected returns before this candidate: their response is
            # expected in its window (the fit and the tests take it as background)
            # (one surface's candidates, later made one, counted once: the first seen)
            once = seen[..., :r].copy()
            for e in range(1, r):
                once[..., e] &= ~(seen[..., :e] & (np.abs(t0_r[..., :e] - t0_r[..., e, None])
                                                   < 3 * sb)).any(-1)
            tails = (t0_r[..., :r], slope[..., :r, :], sig_cnt[..., :r],
                     once & (t0_r[..., :r] < t0[..., None]))
        first = np.maximum(cand_half[..., r], 3.5 * sb)[..., None]
        fit = WIDTH_FIT * sb
        for k_pass, half in enumerate((first, (first + fit) / 2, fit, fit, fit)):
            tq = t0[..., None] + a_s[..., None] * dr + b_s[..., None] * dc
            n0, s1, s2, _, _ = window_sums(tq, half, k_pass >= 2)
            wgt = np.maximum(n0, 0.0)
            # weighted least squares of the photons' times on (1, dr, dc): moments of the
            # net counts (a neighbour's net count may be negative: its weight is 0)
            s1w = np.where(n0 > 0, s1, 0.0)
            M = gram(wgt)
            y = s1w @ X.T
            tot = wgt.sum(-1)
            ridge = 1.0 + 0.01 * tot                          # slopes shrink where few
            M[..., 1, 1] += ridge
            M[..., 2, 2] += ridge
            M[..., 0, 0] += 1e-9
            y[..., 0] += 1e-9 * t0
            beta_fit = np.linalg.solve(M, y[..., None])[..., 0]
            good = tot > 1.0
            t0 = np.where(good, beta_fit[..., 0], t0)
            a_s = np.where(good, beta_fit[..., 1], 0.0)
            b_s = np.where(good, beta_fit[..., 2], 0.0)
        # spread of the photons about the plane, per photon (background left in)
        tq = t0[..., None] + a_s[..., None] * dr + b_s[..., None] * dc
        n0, s1, s2, raw, bsum = window_sums(tq, WIDTH_FIT * sb)
        pos = n0 > 0
        rss = np.where(pos, s2 - 2 * tq * s1 + tq ** 2 * n0, 0.0).sum(-1)
        tot = np.where(pos, n0, 0.0).sum(-1)
        Mfit = gram(np.where(pos, n0, 0.0))
        Minv = np.linalg.inv(Mfit + np.eye(3) * 1e-6)
        # the ridge's pull of the slopes towards 0 moves t0 where the neighbours on the
        # surface are one-sided (an edge): (M + R)^-1 R beta, its first element, squared
        # into the variance (the shrinkage is kept: it steadies the few-photon fits)
        ridge = 1.0 + 0.01 * tot
        Mr = Mfit + np.eye(3) * 1e-6
        Mr[..., 1, 1] += ridge
        Mr[..., 2, 2] += ridge
        Mri = np.linalg.inv(Mr)
        var_ridge = (ridge * (Mri[..., 0, 1] * a_s + Mri[..., 0, 2] * b_s)) ** 2
        var_photon = np.maximum(rss / np.maximum(tot, 1.0), sb ** 2 + 1 / 12)
        # the background photons left in the window move t0 too: their count over the
        # signal's, each with the window's spread
        var_bg = _bg_var(bsum.sum(-1), tot, WIDTH_FIT * sb)
        var_model = var_photon * np.abs(Minv[..., 0, 0]) + var_bg
        # and the sandwich (heteroscedasticity-consistent, HC1) variance of the same fit:
        # every neighbour's leverage on t0 times its photons' summed residual, squared,
        # which takes in what the model leaves out (the background's fluctuation, a
        # surface that is not quite a plane); the larger of the two
        lev = Minv[..., 0, :] @ X
        res = np.where(pos, s1 - tq * n0, 0.0)
        m_eff = np.maximum(pos.sum(-1), 4)
        var_sand = ((lev * res) ** 2).sum(-1) * m_eff / (m_eff - 3)
        # the fit's information (the sandwich's bread) is each neighbour's signal, its
        # expected net count; the positive part that weights the fit credits a
        # neighbour without signal (across a depth edge, beside sky) with its
        # background's positive fluctuation, and at an edge those neighbours sit on
        # one side, where their leverage on t0 is largest. The signed net counts
        # estimate the information without that bias: both variances again with them,
        # the larger kept (where the signed matrix is positive definite)
        Ms = gram(np.where(inside, n0, 0.0)) + np.eye(3) * 1e-6
        pd = np.linalg.det(Ms) > 0
        Msi = np.linalg.inv(np.where(pd[..., None, None], Ms, np.eye(3)))
        pd &= Msi[..., 0, 0] > 0
        lev_s = Msi[..., 0, :] @ X
        var_model = np.where(pd, np.maximum(var_model, var_photon * Msi[..., 0, 0] + var_bg),
                             var_model)
        var_sand = np.where(pd, np.maximum(var_sand, ((lev_s * res) ** 2).sum(-1) * m_eff
                                           / (m_eff - 3)), var_sand)
        # both as if the window were fixed; the fit re-centres it on its own estimate
        # (an M-estimator with psi(u) = u for |u| < c sigma, 0 beyond): Huber's variance
        # E[psi^2] / E[psi']^2 gains the boundary term 2 c phi(c) in E[psi'], a factor
        # (P / (P - 2 c phi(c)))^2 on a Gaussian pulse, P = P(|u| < c): 1.20 at c = 2.5
        # each neighbour's weight on t0 in the fit (the ridge's, as fitted)
        w_t0 = (Mri[..., 0, :] @ X) * np.where(pos, n0, 0.0)
        if cal_q is not None:
            # each neighbour's time axis off by its own calibration error moves all its
            # photons, so t0 by its weight times it: a term of the model's variance; the
            # sandwich's has it already (each neighbour's summed residual holds its error)
            # (not scaled by Huber's factor below: the error moves the photons, not the
            # window's centring)
            var_model = var_model + (w_t0 ** 2 * cal_q).sum(-1) / MSHIFT
        var_t0 = np.maximum(var_model, var_sand) * MSHIFT + var_ridge
        # -- 2b. a depth step inside the window (docs/ranging.md "A small depth step
        # inside the window"): the plane fitted across two surfaces a few pulse widths
        # apart is a ramp between them, off by up to half the step; each half of the
        # window (half-planes through the pixel, :func:`_halves`) fits a plane of its own
        # from the same sums, and the one whose photons spread least about it is the
        # likeliest to lie on one surface (Kuwahara's choice, in Katkovnik's directional
        # windows; the spreads as measured: with the pulse's variance as their floor,
        # the halves below it tied and the first in order, along the columns, won, and
        # a step along the rows lost 20 points of 2-sigma coverage against one along the
        # columns, test_the_step_check_does_not_depend_on_the_steps_direction)
        var_plane = var_t0.copy()   # t0's variance without 2b's bias term (for 2c)
        sv = np.zeros((h, w))       # and what any half's bias adds to the reported sigma
        if STEP_Z:
            # (the 8 halves between the rows, columns and diagonals only where the
            # neighbours hold STEP_FINE net photons each on average: with fewer, the least
            # of 16 spreads is chosen by its noise more than of 8, and more pixels beside a
            # step take the other side's half; fitted only where some pixel has them, apart
            # from the 8, so that every band of rows has the 8's products in one shape)
            fine = (tot >= STEP_FINE * np.maximum(on.sum(-1), 1.0)) & (STEP_FINE > 0)
            k = hm.shape[0] if fine.any() else 8
            fits = [_half_fits(n0, s1, s2, pos, bsum, hm[i:j], X, XX, t0, sb, cal_q)
                    for i, j in ((0, 8), (8, k)) if j > i]
            fits = [np.concatenate(x, -2 if x[0].ndim == t0.ndim + 2 else -1)
                    for x in zip(*fits, strict=True)]
            avail = whole_h[..., :k] & ((np.arange(k) < 8) | fine[..., None])
            kk = np.argmin(np.where(avail, fits[3], np.inf), -1)[..., None]
            whole = np.take_along_axis(avail, kk, -1)[..., 0]
            tk, vm, vr, _, ak, bk = (np.take_along_axis(x, kk, -1)[..., 0] for x in fits[:6])
            hk = hm[kk[..., 0]]                                            # (h, w, m)
            mk = np.take_along_axis(fits[6], kk[..., None], -2)[..., 0, :]
            vk = _half_var(n0 * hk, s1, (tk, ak, bk), mk, vm, vr, X)
            # the half's estimate against the window's, in sds of their difference (a
            # half's photons are the window's: var(t_k - t0) = var_k - var_t0)
            d2 = np.where(whole, (tk - t0) ** 2, 0.0)
            v0 = var_t0
            vd = np.maximum(vk - v0, vk / 4)
            # where they agree, the squared difference less its noise is the bias the
            # window's plane may carry: added to its variance (Lepski's balance of bias
            # against variance; on a surface the plane fits, about vd / 2 on average)
            var_t0 = var_t0 + np.where(d2 > vd, d2 - vd, 0.0)
            if STEP_ANY:
                sv = _step_lean(fits, avail, t0, v0, var_t0)
            # where they do not, and the window's own quadratic misfits its neighbours or
            # two planes, the half's and the rest's, fit them better (a curved surface makes
            # the halves and the window disagree too, and a quadratic follows it), the half
            # is refitted on its own photons and reported
            ii, jj = np.nonzero(d2 > STEP_Z ** 2 * vd)
            n0s, s1s, s2s, ps, hs = (x[ii, jj] for x in (n0, s1, s2, pos, hk))
            chi_q, dof, var_q = _window_quadratic(n0s, s1s, ps, var_photon[ii, jj], X, dr, dc,
                                                  None if cal_q is None else cal_q[ii, jj])
            cs = 1.0 - hs                                                  # the rest
            rest = _half_fits(n0s * cs, s1s * cs, s2s * cs, n0s * cs > 0, bsum[ii, jj] * cs,
                              np.ones((1, dr.size)), X, XX, t0[ii, jj], sb, loops=True)
            plane = np.where(hs > 0, tk[ii, jj, None] + ak[ii, jj, None] * dr
                             + bk[ii, jj, None] * dc,
                             rest[0][:, :1] + rest[4][:, :1] * dr + rest[5][:, :1] * dc)
            chi_2 = (np.where(ps, s1s - n0s * plane, 0.0) ** 2 / var_q).sum(-1)
            keep = _misfits(chi_q, dof) | (chi_q - chi_2 > STEP_TWO)
            ii, jj = ii[keep], jj[keep]
            if ii.size:
                hs = hk[ii, jj]                                            # (p, m)
                t_, a_, b_ = tk[ii, jj], ak[ii, jj], bk[ii, jj]
                sub = [x[ii, jj][:, None] for x in (qn, on, beta_q)]
                for _ in range(STEP_ITER):   # re-centred on its own plane
                    tq_ = (t_[:, None] + a_[:, None] * dr + b_[:, None] * dc)[:, None]
                    if compiled:
                        g_ = _window_sums_numba(P, *sub, tq_, np.full((ii.size, 1), fit), n,
                                                *tables)
                    else:
                        g_ = _window_sums_numpy(P, *sub, tq_, fit, n, prof)
                    n0_, s1_, s2_, _, bs_ = (x[:, 0] * hs for x in g_)
                    fit_ = _half_fits(n0_, s1_, s2_, n0_ > 0, bs_, np.ones((1, dr.size)), X, XX,
                                      t_, sb, None if cal_q is None else cal_q[ii, jj],
                                      loops=True)
                    t_, vm_, vr_, _, a_, b_ = (x[:, 0] for x in fit_[:6])
                m_ = fit_[6][:, 0]
                v_ = _half_var(n0_, s1_, (t_, a_, b_), m_, vm_, vr_, X)
                wk = np.einsum("pi,im->pm", m_, X) * np.where(n0_ > 0, n0_, 0.0)
                ok = (t_ - t0[ii, jj]) ** 2 > STEP_Z ** 2 * np.maximum(v_ - v0[ii, jj], v_ / 4)
                ii, jj = ii[ok], jj[ok]
                t0[ii, jj], var_t0[ii, jj] = t_[ok], v_[ok]
                var_plane[ii, jj] = v_[ok]
                sv[ii, jj] = 0.0
                a_s[ii, jj], b_s[ii, jj] = a_[ok], b_[ok]
                w_t0[ii, jj] = wk[ok]            # its weights: the curvature's step (5)
        # how t0 answers a curvature the plane leaves out, t = ... + (H_rr dr^2 + 2 H_rc
        # dr dc + H_cc dc^2) / 2: those weights times each term (the curvature's step,
        # after the ranking, estimates H)
        bend[..., r, :] = np.stack([(w_t0 * dr ** 2).sum(-1) / 2, (w_t0 * dr * dc).sum(-1),
                                    (w_t0 * dc ** 2).sum(-1) / 2], -1)
        # -- 3. the decision
        half = WIDTH_TEST * sb
        a, z = _window_edges(t0, half, n)
        mine = (np.take_along_axis(P0, z[..., None], -1)
                - np.take_along_axis(P0, a[..., None], -1))[..., 0]
        bw = beta * _span(a, z, prof)
        if tails is not None:   # and the earlier returns' response at the pixel
            bw = bw + _tail_sums(t0[..., None], half, n, response, *tails, np.zeros(1),
                                 np.zeros(1))[0][..., 0]
        own_r = poisson_tail(mine, bw) <= p_fa
        nquad = np.zeros((h, w))
        s_max = np.zeros((h, w))   # the largest of the corner windows' signal a pixel
        for side in QUADRANTS(dr, dc):
            cnt = (raw * side).sum(-1)
            bq = (bsum * side).sum(-1)
            m_q = (inside * side).sum(-1)
            nquad += (poisson_tail(cnt, bq) <= p_fa) & (m_q > 0)
            s_max = np.maximum(s_max, (cnt - bq) / np.maximum(m_q, 1))
        # the pixel's own photons may refuse a surface that surrounds it: fewer in its test
        # window than the best corner window's signal a pixel leaves at p_fa, or fewer in
        # the 3 x 3 around it (its own and its 8 nearest's) than that signal in each of
        # the nine. A sky pixel in a wedge of sky narrower than a right angle, or at a thin
        # gap's end, has all four corner windows see the objects around it (the scene
        # turned by 30 degrees: at (10, 2) 12-13 of 480 empty pixels detected, 0-2 with
        # the pixel's own test; at (5, 2), where no photon of ~5 due is not rare enough
        # alone, 9-12 -> 2-3 with the 3 x 3's)
        # (the pulse's share in the test window over its share in the fit's)
        frac = erf(WIDTH_TEST / np.sqrt(2)) / erf(WIDTH_FIT / np.sqrt(2))
        s_pix = np.maximum(s_max, 0.0)
        ring = (np.abs(dr) <= 1) & (np.abs(dc) <= 1)
        veto = pdtr(np.floor(mine), frac * s_pix + bw) < p_fa
        # and the lines through it (its row, column and diagonals, the window's width):
        # a post or a wire a pixel or two wide before a wall has every corner window
        # mostly wall, and its own few photons cannot refuse it; the line along it can
        # (an outside probe's fence at (2, 10): detected pixels > 10 cm off 552 -> 28 on
        # seed 1; it costs the corner windows' detections within 3 pixels of an edge
        # across a line, at (5, 50) 3,365 -> 3,175 of the grid's scene, then reported
        # by the relabelling; both halves of a line short instead: 552 -> 368, no cost;
        # the whole line short and each half below its mean: the same as the line alone)
        lines = [dr * j == dc * i for i, j in ((0, 1), (1, 0), (1, 1), (1, -1))]
        for near in [ring] + lines:   # fewer photons at t0 than the surface leaves at p_fa
            veto |= (pdtr(np.floor(mine + (raw * near).sum(-1)),
                          frac * s_pix + bw + (bsum * near).sum(-1)
                          + (inside * near).sum(-1) * s_pix) < p_fa)
        quad = (nquad == 4) & ~veto
        found = cand_ok[..., r] & np.isfinite(t0)
        if RISE and r:
            # later than a candidate the window detects: the neighbours' counts must rise
            # over theirs in the gap back to that one's pulse, or in the 2 RISE sigmas
            # just before (a decaying tail rises over neither; "A response's tail is not
            # a second surface" in docs/ranging.md)
            before = np.where(seen[..., :r] & (t0_r[..., :r] < t0[..., None]),
                              t0_r[..., :r], -np.inf).max(-1)
            ii, jj = np.nonzero(found & np.isfinite(before))
            tq = t0[ii, jj, None] + a_s[ii, jj, None] * dr + b_s[ii, jj, None] * dc
            k = RISE * sb
            lead = np.maximum(2 * k, t0[ii, jj] - k - (before[ii, jj] + 3 * sb))
            # (at p_fa over the bins between the two: the places the candidate could take
            # behind the earlier return before its own; over every bin of the histogram,
            # 2-3 photons a pixel 0.5 m behind a 1-ns tail of 100 were found 2-33 % of
            # the time, 6-51 % so)
            gap = np.maximum(t0[ii, jj] - before[ii, jj], 1.0)
            rises = _rises(P, qn[ii, jj], on[ii, jj], beta_q[ii, jj], tq, k, lead, n, prof,
                           p_fa / gap)
            if response is None:
                found[ii, jj] = rises
            else:
                # above the earlier returns' measured response there (a peaked delay's
                # bump rises), and the rise test too where the response falls short of
                # the counts just before ("A measured response" in docs/ranging.md)
                above, trusted = _above_response(
                    P, qn[ii, jj], on[ii, jj], beta_q[ii, jj], tq, k, lead,
                    t0[ii, jj] - k - (before[ii, jj] + 3 * sb), n, prof,
                    p_fa / gap, response, t0_r[ii, jj, :r], slope[ii, jj, :r],
                    sig_cnt[ii, jj, :r],
                    tails[3][ii, jj] & (t0_r[ii, jj, :r] < t0[ii, jj, None]), dr, dc)
                found[ii, jj] &= above & (trusted | rises)
        slope[..., r, 0], slope[..., r, 1] = a_s, b_s
        mine_r[..., r], bw_r[..., r] = mine, bw
        # -- 2c. the pixel's own photons, a second estimate of its time (after the
        # decision: 3 tested the plane's window, its p_fa holds). Beside a step that
        # crosses the window at an angle none of the halves follows, or within half a
        # pixel of one, no half is one surface and every half's plane is off; the
        # pixel's own photons are not. Where the two differ by more than ``OWN_Z`` sds,
        # their squared difference less its noise is the bias t0 may carry, as 2b's
        # (the larger of the two is kept). t0 stays the plane's: the pixel's own photons
        # would carry its own calibration error, which the plane averages over its
        # neighbours (test_sigma_covers_the_neighbours_calibration_errors). Only where
        # its own photons detect the pixel (3), not its corner windows alone
        if OWN_Z:
            ii, jj, bias = _own_bias(P, beta, t0, var_plane, var_photon, found & own_r, fit, n,
                                     prof, None if cal_var is None else cal_var / bin_s ** 2)
            var_t0[ii, jj] = np.maximum(var_t0[ii, jj], var_plane[ii, jj] + bias)
        # -- 2d. a surface the neighbours do not hold: their counts about the plane are
        # no detection at ``p_fa`` (a lone point, a retroreflector or a post's tip,
        # before a wall or in the sky). The plane is then their background's, its time
        # and sigma noise's (40 photons in one wall pixel 2 m away at (2, 50): 8 cm off,
        # sigma 4.5 cm; at (2, 0.001): sigma 31 m), and the candidate's time the window
        # box's (without background every box that holds the point scores alike: 8
        # pulse sigmas early). The pixel's own photons' mean, re-centred from the
        # candidate as step 2 re-centres the plane (from t0 on the fit's window where 3
        # detected the pixel), gives t0, their spread over their number its variance
        # (and the pixel's calibration's); and the pixel is detected
        # where 3 detected it, or where its counts in the test window about that mean
        # are a detection at ``p_fa`` over the window's places the re-centring could
        # choose (the candidate's box: the union bound). Not where the neighbours' counts
        # about that mean (over the candidate's box) are a detection: a surface the plane
        # missed, not a lone one (a grazing floor at (2, 10): 1,426 -> 1,473 pixels > 10
        # cm off on the outside probe's seeds 1-3 without this). (On
        # Lindell's grid, where every surface spans many pixels, one pixel in 75
        # frames of the grid's scene at (2, 50); benchmarks/spatial_points.py)
        if LONE:
            held = poisson_tail(raw.sum(-1), bsum.sum(-1)) <= p_fa
            cal_b = None if cal_var is None else cal_var / bin_s ** 2
            # detected by 3: from t0 on the fit's window; else from the candidate
            i1, j1, m1, v1, _, _ = _own_mean(P, beta, t0, None, found & ~held & own_r, fit, n,
                                             prof, cal_b)
            i2, j2, m2, v2, _, _ = _own_mean(P, beta, cand[..., r] + 0.5, None,
                                             found & ~held & ~own_r, fit, n, prof, cal_b,
                                             first[..., 0])
            tt = np.full((h, w, 1), np.nan)
            tt[i2, j2, 0] = m2
            mine2, a1, z1 = (x[i2, j2, 0] for x in _window_counts(P0, tt, half))
            bw2 = beta[i2, j2] * _span(a1, z1, prof)
            det2 = poisson_tail(mine2, bw2) <= p_fa / (2 * first[i2, j2, 0] + 1)
            ii, jj = np.concatenate([i1, i2[det2]]), np.concatenate([j1, j2[det2]])
            m, v = np.concatenate([m1, m2[det2]]), np.concatenate([v1, v2[det2]])
            # and not where the neighbours hold a surface about the pixel's own time (the
            # candidate's box, flat): one the plane missed (a grazing floor), not a lone
            # one
            _, _, _, raw_m, bsum_m = _window_sums_numpy(
                P, qn[ii, jj], on[ii, jj], beta_q[ii, jj], m[:, None], first[ii, jj], n, prof)
            lone = poisson_tail(raw_m.sum(-1), bsum_m.sum(-1)) > p_fa
            k2 = np.zeros(i2.size, bool)
            k2[det2] = lone[i1.size:]
            ii, jj, m, v = ii[lone], jj[lone], m[lone], v[lone]
            mine_r[i2[k2], j2[k2], r], bw_r[i2[k2], j2[k2], r] = mine2[k2], bw2[k2]
            mine[i2[k2], j2[k2]], bw[i2[k2], j2[k2]] = mine2[k2], bw2[k2]
            own_r[i2[k2], j2[k2]] = True
            t0[ii, jj], var_t0[ii, jj] = m, v
            sv[ii, jj] = 0.0
        # (a candidate the window does not detect still gives the pixel a distance, as a
        # per-pixel estimator's undetected peak does; it is never detected)
        t_out[..., r] = np.where(np.isfinite(t0), t0 * bin_s + t0_s, np.nan)
        t0_r[..., r] = t0
        sig_out[..., r] = np.sqrt(var_t0) * bin_s
        lean[..., r] = sv
        sig_cnt[..., r] = tot / np.maximum(inside.sum(-1), 1)
        own[..., r] = found & own_r
        # (ranking by the excess counts of the pixel and its 8 nearest instead of its own
        # left more pixels > 10 cm off in most cells of Lindell's grid: not kept)
        # (the pixel's own detection first: a surface its corner windows see and its own
        # photons do not, beside a depth edge, is the neighbours' more than its own; the
        # scene turned by 30 degrees at (10, 50): 10 pixels > 10 cm off with a wrong
        # first return and the right one second)
        rank[..., r] = (np.where(found, 0.0, -1e8) + (found & own_r) * 1e7 + nquad * 1e6
                        + (mine - bw) * 1e3 + sig_cnt[..., r])
        surr[..., r] = found & quad
        seen[..., r] = found
    # two candidates that settled on one surface are one
    for r in range(1, nc):
        for s in range(r):
            same = np.abs(t_out[..., r] - t_out[..., s]) < 3 * sigma_s
            for arr, v in ((t_out, np.nan), (own, False), (surr, False), (sig_cnt, 0.0),
                           (rank, -1e9), (seen, False)):
                arr[..., r] = np.where(same, v, arr[..., r])
    return (t_out, sig_out, sig_cnt, own | surr, own, surr, slope, mine_r, bw_r, rank, beta, P0,
            bend, seen, lean)


def _step_lean(fits, avail, t0, v0, var_t0):
    """2b's bias term from any of the 8 half-planes, not only the one whose photons
    spread least: the largest d_k^2 - vd_k over the halves whose plane lies more than
    ``STEP_ANY`` sds (of the difference, as 2b's) from the window's, less what 2b added
    already (bins^2; 0 where none does). Beside a step under about 2 pulse sigmas a half
    across it spreads its photons about as little as the half on one side (a ramp fits
    both), so the least spread often picks a half as biased as the window, and the bias
    went unseen: stripes 3 cm apart at (10, 2), 2 sigma covered 57 % of the columns
    beside the edge (bias 0.7-1.1 cm against a sigma of 0.3). ``fits``: 2b's
    :func:`_half_fits` over its halves (the first 8: the rows', the columns' and the
    diagonals' sides); their variance is the model's (no sandwich), times Huber's
    factor, and the ridge's pull."""
    vk = fits[1][..., :8] * MSHIFT + fits[2][..., :8]
    dk = np.where(avail[..., :8], (fits[0][..., :8] - t0[..., None]) ** 2, 0.0)
    vd = np.maximum(vk - v0[..., None], vk / 4)
    ex = np.where(dk > STEP_ANY ** 2 * vd, dk - vd, 0.0).max(-1)
    return np.maximum(v0 + ex - var_t0, 0.0)


def _bg_var(bsum, n, fit):
    """The variance a mean of ``n`` net photons (at least 1) takes from the ``bsum``
    background photons left in its window of +- ``fit`` bins (each uniform over it,
    variance fit^2 / 3): step 2's, 2b's halves' and 2c's."""
    return (bsum * fit ** 2 / 3) / np.maximum(n, 1.0) ** 2


def _halves(dr, dc) -> np.ndarray:
    """The window's 16 halves through the pixel, each with its middle line: (16, m) masks
    over the offsets (dr, dc), both sides of a line at 8 directions. The first 8 along a
    column, a row and the two diagonals, then the 8 between them (at 22.5 degrees to
    those). A half holds every offset on its side of the line and on the line's digital
    trace: within half a pixel of the line along the axis it runs nearer to (one offset
    a column or a row; the column, row or diagonal itself where the line is one)."""
    out = []
    for a in np.pi * np.array([0.5, 0.0, 0.25, -0.25, 0.125, 0.375, 0.625, 0.875]):
        p = dr * np.cos(a) + dc * np.sin(a)
        band = 0.5 * max(abs(np.cos(a)), abs(np.sin(a))) + 1e-9
        out += [p <= band, p >= -band]
    return np.stack(out).astype(np.float64)


def _half_fits(n0, s1, s2, pos, bsum, hm, X, XX, t0, sb, cal=None, loops=False):
    """Step 2's plane fit (its ridge on the slopes) over each half ``hm`` (k, m) of the
    window, from the sums at the window's plane, all halves in a few matrix products:
    per half (..., k), its t0, t0's model variance (as step 2's: the photons' spread, at
    least the pulse's, and the background's, before Huber's factor), the ridge's pull's,
    the photons' spread about its plane (as measured: no floor, which would tie the
    halves' spreads below it), its slopes, and the first row of its inverse normal
    matrix (..., k, 3). The photons' spread follows from the sums: rss = S2 - 2 b.Y +
    b' M b. ``cal``
    (..., m), each neighbour's calibration variance (bins^2), adds its share, as step 2's.
    ``loops``: the products in einsum's loops (a few pixels' fits: bands of rows agree to
    the bit)."""
    k, m = hm.shape
    wq = np.where(pos, n0, 0.0)

    def dot(a, b):  # (``loops``: einsum's own loops, a pixel's sums the same in a batch
        # of any size, where a BLAS product's order may follow a few rows' shape)
        return np.einsum("...m,mk->...k", a, b) if loops else a @ b
    M0 = dot(wq, (hm[:, :, None] * XX[None]).transpose(1, 0, 2).reshape(m, 9 * k)
             ).reshape(wq.shape[:-1] + (k, 3, 3))
    Y = dot(np.where(pos, s1, 0.0), (hm[:, :, None] * X.T[None]).transpose(1, 0, 2)
            .reshape(m, 3 * k)).reshape(wq.shape[:-1] + (k, 3))
    S2 = dot(np.where(pos, s2, 0.0), hm.T)
    tot = dot(wq, hm.T)
    ridge = 1.0 + 0.01 * tot
    # the symmetric 3 x 3 normal matrix with the ridge, inverted by its cofactors (one
    # pass over the arrays; LAPACK's batched inverse of so many small ones is slower)
    m00, m01, m02 = M0[..., 0, 0] + 1e-9, M0[..., 0, 1], M0[..., 0, 2]
    m11, m12, m22 = M0[..., 1, 1] + ridge, M0[..., 1, 2], M0[..., 2, 2] + ridge
    c00, c01, c02 = m11 * m22 - m12 * m12, m02 * m12 - m01 * m22, m01 * m12 - m02 * m11
    c11, c12, c22 = m00 * m22 - m02 * m02, m01 * m02 - m00 * m12, m00 * m11 - m01 * m01
    det = m00 * c00 + m01 * c01 + m02 * c02
    Mi = np.stack([np.stack([c00, c01, c02], -1), np.stack([c01, c11, c12], -1),
                   np.stack([c02, c12, c22], -1)], -2) / det[..., None, None]
    Y1 = Y.copy()
    Y1[..., 0] += 1e-9 * t0[..., None]
    b = (Mi * Y1[..., None, :]).sum(-1)
    rss = S2 - 2 * (b * Y).sum(-1) + (b[..., :, None] * M0 * b[..., None, :]).sum((-2, -1))
    spread = rss / np.maximum(tot, 1.0)
    vp = np.maximum(spread, sb ** 2 + 1 / 12)
    vbg = _bg_var(dot(bsum, hm.T), tot, WIDTH_FIT * sb)
    vr = (ridge * (Mi[..., 0, 1] * b[..., 1] + Mi[..., 0, 2] * b[..., 2])) ** 2
    var = vp * Mi[..., 0, 0] + vbg
    if cal is not None:  # sum_q (Mi0 . X_q n0_q)^2 cal_q, per half (as step 2's, unscaled)
        Cq = dot(wq ** 2 * cal, (hm[:, :, None] * XX[None]).transpose(1, 0, 2)
                 .reshape(m, 9 * k)).reshape(wq.shape[:-1] + (k, 3, 3))
        var = var + np.einsum("...ki,...kij,...kj->...k", Mi[..., 0, :], Cq,
                              Mi[..., 0, :]) / MSHIFT
    return b[..., 0], var, vr, spread, b[..., 1], b[..., 2], Mi[..., 0, :]


def _half_var(n0, s1, plane, mi0, var_model, var_ridge, X):
    """t0's variance of one half's plane (``n0`` 0 outside it), as step 2's: the larger
    of the model's variance and the sandwich's (each neighbour's leverage on t0 times its
    photons' summed residual about the plane: what the model leaves out, a neighbour's
    calibration error or a surface that is not a plane), times Huber's factor, and the
    ridge's pull."""
    t, a, b = plane
    use = n0 > 0
    tq = t[..., None] + a[..., None] * X[1] + b[..., None] * X[2]
    res = np.where(use, s1 - tq * n0, 0.0)
    lev = np.einsum("...i,im->...m", mi0, X)
    m_eff = np.maximum(use.sum(-1), 4)
    var_sand = ((lev * res) ** 2).sum(-1) * m_eff / (m_eff - 3)
    return np.maximum(var_model, var_sand) * MSHIFT + var_ridge


def _misfits(chi, dof) -> np.ndarray:
    """A chi-square ``STEP_LOF`` sds above its degrees of freedom."""
    return chi > dof + STEP_LOF * np.sqrt(2 * dof)


def _own_mean(P, beta, t0, var_photon, sel, fit, n, prof=None, cal=None, first=None):
    """The pixels of ``sel``'s own photons' mean, re-centred ``STEP_ITER`` + 1 times
    from t0 on its own window (+- ``fit`` bins; ``first`` (h, w): the first step's
    half-width, the second's half way to ``fit``, as step 2's), and its variance: the
    photons' spread (``var_photon`` (h, w), bins^2; None: their own about the mean, at
    least the pulse's) over their number and the background's as step 2's, and the pixel's
    calibration variance ``cal`` (h, w) in bins^2 where given. Returns their rows and
    columns, the means, the variances, and the net and raw counts in the window."""
    h, w = t0.shape
    ii, jj = np.nonzero(sel & np.isfinite(t0))
    qs = (ii * w + jj)[:, None] * (n + 1)              # the pixel's own prefix sums' row
    one, bq = np.ones((ii.size, 1)), beta[ii, jj][:, None]
    m = t0[ii, jj]
    widths = [fit] * (STEP_ITER + 1)
    if first is not None:
        f = first[ii, jj][:, None]
        widths[:2] = [f, (f + fit) / 2]
    for half in widths:
        n0, s1, s2, raw, bs = (x[:, 0] for x in _window_sums_numpy(P, qs, one, bq, m[:, None],
                                                                    half, n, prof))
        c = n0 > 0
        m = np.where(c, s1 / np.where(c, n0, 1.0), m)
    if var_photon is None:
        vp = np.where(c, s2 / np.where(c, n0, 1.0) - m ** 2, 0.0)
        vp = np.maximum(vp, (fit / WIDTH_FIT) ** 2 + 1 / 12)   # the pulse's, the least
    else:
        vp = var_photon[ii, jj]
    v = (vp / np.maximum(n0, 1.0) + _bg_var(bs, n0, fit)) * MSHIFT
    v = v + (0.0 if cal is None else cal[ii, jj])
    return ii, jj, m, v, n0, raw


def _own_bias(P, beta, t0, var_plane, var_photon, sel, fit, n, prof=None, cal=None):
    """2c. For the pixels of ``sel``: their own photons' mean (:func:`_own_mean`)
    against t0. Where they differ by more than ``OWN_Z`` sds (the mean's variance plus
    t0's ``var_plane``), with ``OWN_MIN`` counts in the window at least, the squared
    difference less that variance. Returns their rows, columns and those biases
    (bins^2)."""
    ii, jj, m, v, n0, raw = _own_mean(P, beta, t0, var_photon, sel, fit, n, prof, cal)
    v = v + var_plane[ii, jj]
    d2 = (m - t0[ii, jj]) ** 2
    ok = (n0 > 0) & (raw >= OWN_MIN) & (d2 > OWN_Z ** 2 * v)
    return ii[ok], jj[ok], d2[ok] - v[ok]


def _misfit(n0, s1, pos, var_photon, X, dr, dc, cal=None) -> np.ndarray:
    """Whether the window's quadratic (:func:`_window_quadratic`) misfits."""
    return _misfits(*_window_quadratic(n0, s1, pos, var_photon, X, dr, dc, cal)[:2])


def _window_quadratic(n0, s1, pos, var_photon, X, dr, dc, cal=None):
    """A quadratic in (dr, dc) fitted to the neighbours' photon times, and how far it
    misses their means against their noise: the chi-square of each neighbour's summed
    residual over its variance (its count times the photons' spread, and with ``cal``,
    each neighbour's calibration variance in bins^2, its count squared times that: a
    time axis off by its own error moves all its photons), its degrees of freedom, and
    those variances (..., m). A surface that curves fits; a step inside the window
    (which no quadratic follows) does not."""
    X6 = np.concatenate([X, np.stack([dr ** 2 / 2, dr * dc, dc ** 2 / 2])])   # (6, m)
    XX6 = (X6[:, None, :] * X6[None, :, :]).reshape(36, -1).T
    wq = np.where(pos, n0, 0.0)
    # (einsum's loops: run on the pixels the halves flag, a batch whose size differs
    # between bands of rows and the whole image; see _half_fits)
    M = np.einsum("...m,mk->...k", wq, XX6).reshape(wq.shape[:-1] + (6, 6))
    ridge = 1.0 + 0.01 * wq.sum(-1)
    for i in range(1, 6):
        M[..., i, i] += ridge
    M[..., 0, 0] += 1e-9
    y = np.einsum("...m,km->...k", np.where(pos, s1, 0.0), X6)
    beta = np.linalg.solve(M, y[..., None])[..., 0]
    res = np.where(pos, s1 - n0 * np.einsum("...k,km->...m", beta, X6), 0.0)
    var = np.maximum(n0, 1.0) * var_photon[..., None]
    if cal is not None:
        var = var + np.maximum(n0, 0.0) ** 2 * cal
    chi = (res ** 2 / var).sum(-1)
    return chi, np.maximum(pos.sum(-1) - 6, 1), var


@dataclass(frozen=True)
class SpatialResponse:
    """The instrument's response behind a return, measured for this estimator (not
    :class:`stages.ranging.irf.Response`, the per-pixel estimators' density of one
    return's photons: this one is read against the spatial estimate's own signal counts
    and return bin, which the tests below compare it with): ``share[i]`` the expected
    counts in bin floor(t) + ``first`` + i of a return at t (bins) a count of its
    ``signal_counts`` (the estimate's, so that the two are read alike), the background
    out; 0 outside; on bins of ``bin_s`` (a frame on other bins is refused). A pulse's
    own Gaussian core and whatever a SPAD adds behind it (a diffusion tail, a peaked
    delay, an afterpulse)."""

    first: int
    share: np.ndarray
    bin_s: float


def measure_response(counts: np.ndarray, est: SpatialEstimate, bin_s: float,
                     t0_s: float = 0.0, before_s: float | None = None,
                     after_s: float | None = None) -> SpatialResponse:
    """:class:`SpatialResponse` from a frame of one return a pixel (a target at the zero, or any
    flat one) and its :func:`spatial` estimate: over the detected first returns, the
    counts at each bin offset from the return's bin less the pixel's background, over
    the returns' signal counts; from ``before_s`` (default 1 ns) before to ``after_s``
    after (default: to the histograms' end; an afterpulse 10 ns behind was missed with
    8 ns, and 98 % of the pixels had a false surface). A bin offset no
    return's histogram reaches stays 0. Negative shares (the background's noise) are
    0: the expected response is then a little high, which only withdraws a later
    return. Refused where no pixel is detected."""
    counts = np.asarray(counts, np.float64)
    n = counts.shape[-1]
    det = est.detected[..., 0] & np.isfinite(est.t_s[..., 0]) & (est.signal_counts[..., 0] > 0)
    if not det.any():
        raise ValueError("measure_response: no detected return in the frame")
    first = -int(np.ceil((1e-9 if before_s is None else before_s) / bin_s))
    r, c = np.nonzero(det)
    f = np.floor((est.t_s[r, c, 0] - t0_s) / bin_s).astype(np.int64)
    length = (max(n - int(f.min()), 1) if after_s is None
              else int(np.ceil(after_s / bin_s))) - first
    idx = f[:, None] + first + np.arange(length)                 # (p, length)
    inside = (idx >= 0) & (idx < n)
    got = np.where(inside, counts[r[:, None], c[:, None], np.clip(idx, 0, n - 1)]
                   - est.background_per_bin[r, c, 0][:, None], 0.0)
    sig = np.where(inside, est.signal_counts[r, c, 0][:, None], 0.0)
    share = np.where(sig.sum(0) > 0, got.sum(0) / np.maximum(sig.sum(0), 1e-300), 0.0)
    return SpatialResponse(first, np.maximum(share, 0.0), float(bin_s))


def _tail_sums(tq, half, n, response, t_e, sl_e, s_e, use, dr, dc):
    """What the earlier returns ``use`` (..., e) leave, by the measured response, in each
    neighbour's window of +-``half`` bins about ``tq`` (..., m) (clipped as the window
    sums clip it): its counts, and their sums of bin-time and of its square (the window
    sums' moments), each (..., m). An earlier return: its signal a pixel ``s_e``, its
    plane (``t_e`` bins, slopes ``sl_e`` (..., e, 2)) read at each neighbour."""
    a, z = _window_edges(tq, half, n)
    sh = response.share
    i = np.arange(sh.size, dtype=np.float64)
    R0, R1, R2 = (np.concatenate([[0.0], np.cumsum(x)]) for x in (sh, sh * i, sh * i * i))
    L = sh.size
    T0, T1, T2 = (np.zeros(tq.shape) for _ in range(3))
    for e in range(t_e.shape[-1]):
        te = (t_e[..., e, None] + sl_e[..., e, 0, None] * dr + sl_e[..., e, 1, None] * dc)
        f = np.floor(np.where(np.isfinite(te), te, 0.0)).astype(np.int64) + response.first
        lo, hi = np.clip(a - f, 0, L), np.clip(z - f, 0, L)
        c = f + 0.5                                   # bin f + i's time is c + i
        m0, m1, m2 = R0[hi] - R0[lo], R1[hi] - R1[lo], R2[hi] - R2[lo]
        s = np.where(use[..., e] & np.isfinite(s_e[..., e]), s_e[..., e], 0.0)[..., None]
        T0 += s * m0
        T1 += s * (m1 + c * m0)
        T2 += s * (m2 + 2 * c * m1 + c * c * m0)
    return T0, T1, T2


def _above_response(P, qn, on, beta_q, tq, k, lead, room, n, prof, alpha, response, t_e,
                    sl_e, s_e, use, dr, dc) -> tuple[np.ndarray, np.ndarray]:
    """Step 3 where the response is measured (:class:`SpatialResponse`): whether the neighbours'
    counts within +-``k`` bins of the later return's plane (``tq``, (p, m) bins) stand
    above, at ``alpha``, their background plus what each earlier return ``use`` (p, e)
    leaves there (:func:`_tail_sums`). The null's counts are Poisson about that sum,
    whatever the response's shape: a peaked delay's bump is expected, a surface behind
    a tail stands out of it (the rise test cannot see a bump, and loses a weak surface
    in a tail). And whether the response holds just before: the counts in the rise
    test's two earlier windows (the ``lead`` (p,) bins before, and the 2 ``k`` before)
    are no more than it expects there, each at ``RESPONSE_CHECK`` (a response measured
    short of the capture's tail, another instrument's or another day's, left 2-99 % of
    the pixels with a false surface; where it falls short, the caller asks the rise
    test too). Only behind the earlier pulse's core: ``room`` (p,), the bins between its
    3 sigma and the window, must hold both windows (nearer, they hold the core, which
    any response with the right pulse fits, a tail or not). Returns both (p,)."""
    def expected(t, half):
        _, _, _, c, b = _window_sums_numpy(P, qn, on, beta_q, t, half, n, prof)
        tail = _tail_sums(t, half, n, response, t_e, sl_e, s_e, use, dr, dc)[0]
        return c.sum(-1), b.sum(-1) + (tail * on).sum(-1)

    above = poisson_tail(*expected(tq, k)) <= alpha
    trusted = room >= 2 * k
    for lp_ in (lead, np.full(len(tq), 2.0 * k)):
        hp = lp_[:, None] / 2
        trusted &= poisson_tail(*expected(tq - k - hp, hp)) > RESPONSE_CHECK
    return above, trusted


def _rises(P, qn, on, beta_q, tq, k, lead, n, prof, alpha) -> np.ndarray:
    """Whether the neighbours' counts within +-``k`` bins of their plane (``tq``: (p, m)
    times, bins) stand above their counts just before, at ``alpha``: in the ``lead``
    (p,) bins before (the gap back to the earlier return's pulse, at least 2 ``k``: power
    where the gap holds background alone) or in the 2 ``k`` bins before (power where a
    tail fills the gap), each at ``alpha`` / 2. Each the binomial split of the two
    windows' sum (two Poisson counts, the test conditional on their sum), under the null
    that the later window's mean a bin is no larger than the earlier's (a tail that
    decays: a SPAD's diffusion tail behind a return; the background's share where it is
    larger, a profile not flat in time). Closer than 2 ``k`` to the earlier pulse, the
    window holds that pulse's edge, and the candidate does not rise over it."""
    def bins(t, half):  # the window's bins over the neighbours, as the sums clip them
        a, z = _window_edges(t, half, n)
        return ((z - a) * on).sum(-1)

    _, _, _, cc, bc = _window_sums_numpy(P, qn, on, beta_q, tq, k, n, prof)
    lc, cc, bc = bins(tq, k), cc.sum(-1), bc.sum(-1)
    p = np.ones(len(tq))
    for lp_ in (lead, np.full(len(tq), 2.0 * k)):
        hp = lp_[:, None] / 2
        _, _, _, cp, bp = _window_sums_numpy(P, qn, on, beta_q, tq - k - hp, hp, n, prof)
        p = np.minimum(p, rise_p(cc, cp.sum(-1), bc, bp.sum(-1), lc, bins(tq - k - hp, hp)))
    return p <= alpha / 2


def _window_edges(t, half, n):
    """The bins [a, z) of a window of +-``half`` about ``t`` (bins), clipped to [0, n]:
    the window sums' (and the numba kernel's) rule."""
    return (np.clip(np.floor(t - half + 0.5).astype(np.int64), 0, n),
            np.clip(np.floor(t + half + 0.5).astype(np.int64), 0, n))


def _window_sums_numpy(P, qn, on, beta_q, tq, half, n, prof=None):
    """Per pixel and neighbour (h, w, m): the counts, sums of bin-time and of its square
    in tq +- half (bins), background subtracted, and the raw counts and the background,
    from the (count, time, time^2) prefix sums ``P`` (rows qn + bin)."""
    a, z = _window_edges(tq, half, n)
    g = (np.take(P, qn + z, 0) - np.take(P, qn + a, 0)) * on[..., None]  # (h, w, m, 3)
    raw, s1, s2 = g[..., 0], g[..., 1], g[..., 2]
    if prof is None:
        bsum = beta_q * (z - a)
        mid1 = beta_q * (z * z - a * a) / 2.0                 # sum of (j + 0.5) over the bins
        mid2 = beta_q * ((z ** 3 - a ** 3) / 3.0 - (z - a) / 12.0)  # of (j + 0.5)^2
    else:  # the background's profile: its sums, of (j + 0.5) and of (j + 0.5)^2
        bsum, mid1, mid2 = (beta_q * (S[z] - S[a]) for S in prof[1:])
    return raw - bsum, s1 - mid1, s2 - mid2, raw, bsum


if numba is not None:
    @numba.njit(cache=True, nogil=True)
    def _window_sums_numba(P, qn, on, beta_q, tq, half, n, flat, S0, S1, S2):
        """:func:`_window_sums_numpy` in one pass, without its temporaries (the same
        operations in the same order: equal results); ``half`` (h, w)."""
        h, w, m = tq.shape
        n0 = np.empty((h, w, m))
        s1 = np.empty((h, w, m))
        s2 = np.empty((h, w, m))
        raw = np.empty((h, w, m))
        bsum = np.empty((h, w, m))
        for i in range(h):
            for j in range(w):
                hf = half[i, j]
                for k in range(m):
                    t = tq[i, j, k]
                    a = min(max(np.int64(np.floor(t - hf + 0.5)), 0), n)
                    z = min(max(np.int64(np.floor(t + hf + 0.5)), 0), n)
                    qa, qz, o, bq = qn[i, j, k] + a, qn[i, j, k] + z, on[i, j, k], beta_q[i, j, k]
                    r = (P[qz, 0] - P[qa, 0]) * o
                    b = bq * (z - a) if flat else bq * (S0[z] - S0[a])
                    raw[i, j, k] = r
                    bsum[i, j, k] = b
                    n0[i, j, k] = r - b
                    if flat:
                        s1[i, j, k] = (P[qz, 1] - P[qa, 1]) * o - bq * (z * z - a * a) / 2.0
                        s2[i, j, k] = ((P[qz, 2] - P[qa, 2]) * o
                                       - bq * ((z ** 3 - a ** 3) / 3.0 - (z - a) / 12.0))
                    else:
                        s1[i, j, k] = (P[qz, 1] - P[qa, 1]) * o - bq * (S1[z] - S1[a])
                        s2[i, j, k] = (P[qz, 2] - P[qa, 2]) * o - bq * (S2[z] - S2[a])
        return n0, s1, s2, raw, bsum


def _finish(fields, max_returns, bin_s, sb, t0_s, prof=None, compiled=None,
            threads=1, p_fa=None) -> SpatialEstimate:
    """3b and the order of the returns, on the whole image (the relabelling's sweeps
    reach further than a band's halo)."""
    t_out, sig_out, sig_cnt, det, own, surr, slope, mine_r, bw_r, rank, beta, P0, bend, seen, \
        lean = fields

    def slot(x, v):  # one more slot a pixel: a neighbour's plane carried over (3b)
        return np.concatenate([x, np.full(x.shape[:2] + (1,) + x.shape[3:], v, x.dtype)], 2)

    t_out, sig_out, sig_cnt, det, own, surr = (
        slot(x, v) for x, v in ((t_out, np.nan), (sig_out, np.inf), (sig_cnt, 0.0),
                                (det, False), (own, False), (surr, False)))
    # a surface only the corner windows detect does not hold the pixel: it is labelled
    # as an undetected one (the frame's planes are still found from every detection),
    # and the detection stands where the label lies on its surface, else it is
    # withdrawn (not detected; the label reported). A plane fitted across two surfaces
    # (a pane above the slanted floor: t0 21 bins off) passes the corner windows.
    rank, state = _relabel(t_out, sig_out, slot(slope, 0.0), slot(mine_r, 0.0),
                           slot(bw_r, 0.0), sig_cnt, slot(rank, -1e9), own, P0, beta,
                           bin_s, sb, t0_s, prof, compiled, det, threads, p_fa)
    lab, free, tb = state[:3]
    # a detection the edges' lines doubt (its own photons against the line's photons
    # all along the edge: stages/ranging/edgelines.py) is withdrawn, the pixel labelled
    doubted, p_was, t_was, line_var, island = state[7]
    own = own & ~doubted[..., None]
    surr_only = surr & ~own
    tl = np.take_along_axis(tb, lab[..., None], -1)[..., 0]
    # (the labels' tolerance, 3 sigma of the pulse, as the relabelling's. A pixel its
    # own photons hold keeps its corner windows' surfaces as further returns, and so
    # does one whose label lies on one of them (its other corner windows' surfaces: a
    # two-surface pixel's second one; withdrawing those, seeds 1-2 of both scenes at
    # (2, 10), (2, 50), (5, 10), (5, 50), took the second returns detected within 10
    # cm of a true surface from 1,142 to 606 and those off from 37 to 31; the first
    # returns are the same). Also withdrawing it where the cut, whose labels include
    # "no surface", calls the pixel empty took the turned scene's false surfaces at
    # seeds 1-3 from 42 to 36 of 11,520 empty pixels, and 5 of 65 true detections at 2
    # signal photons on the LinoSPAD2 background: not done)
    near = np.abs((t_out - t0_s) / bin_s - tl[..., None]) < 3.0 * sb
    held = free & (surr_only & near).any(-1)     # a detection stands: its own fit, sigma
    stand = surr_only & (~free | held)[..., None]
    det = own | stand
    surr = surr & (own | stand)
    # a held pixel's label loses its place first (its detection on the label's surface
    # takes it: the label is not repeated as a further return), and that detection is
    # reported before the pixel's other surfaces
    rank = np.where(held[..., None], rank - np.where(rank >= 1e10, 1e11, 0.0)
                    + np.where(near & stand, 1e10, 0.0), rank)
    _label_sigma((lab, free & ~held) + state[2:7], sig_cnt, sig_out, P0, beta, bin_s, sb,
                 prof)
    # the surface's doubt, added last (after the curvature's step has put a quadratic's
    # time and sigma in place of an undetected pixel's plane where they agree: the
    # surface's question, not the time's on it): a doubted detection's pixel, the
    # chance it lies on the surface it was detected on (its posterior against the
    # line's) times the squared distance between the two; an undetected pixel a line
    # weighed, the chance it lies on the pair's other plane (stages/ranging/edgelines.py)
    # (on the first return: the label's slot, or where a detection on the label's
    # surface holds the pixel, that detection)
    extra = np.zeros(free.shape)
    rd, cd = np.nonzero(doubted | island)
    extra[rd, cd] = p_was[rd, cd] * ((t_was[rd, cd] - tb[rd, cd, lab[rd, cd]]) * bin_s) ** 2
    line = free & ~held & ~doubted & ~island
    extra[line] = line_var[line] * bin_s ** 2
    # detected before not; then by the corner windows that see the surface, then by the
    # pixel's own excess counts, then by the neighbourhood's signal. But an island's
    # label (or the detection on its surface that holds it) before its own detection,
    # which stays a further return (:func:`_islands`)
    key = np.where(det, 1e12, 0.0) + rank
    ri, ci = np.nonzero(island)
    was = np.full(island.shape, np.nan)   # an island's detection: its first return before
    was[ri, ci] = t_was[ri, ci] * bin_s + t0_s
    key[ri, ci, np.argmax(rank[ri, ci], -1)] += 5e12
    order = np.argsort(-key, axis=-1, kind="stable")[..., :max_returns]

    def take(x):
        return np.take_along_axis(x, order, -1)

    # the candidates' times before the order, and those the pixel's window detects (6)
    cand = (t_out[..., :seen.shape[-1]], seen)
    t_out, sig_out, det = take(t_out), take(sig_out), take(det)
    # (the carried plane's slot is no fit: no curvature step)
    bend = np.take_along_axis(slot(bend, 0.0), order[..., None], 2)
    _curvature(t_out, sig_out, det, bend, bin_s, sb, t0_s)
    sig_cnt = take(sig_cnt)
    before6 = sig_out[..., 0] ** 2
    _off_surface(t_out, sig_out, det, sig_cnt, P0, beta, bin_s, sb, t0_s, prof, cand, was,
                 state[8] if OFF_PLANES else None)
    with np.errstate(invalid="ignore"):
        added6 = np.where(np.isfinite(before6), sig_out[..., 0] ** 2 - before6, 0.0)
    # 2b's lean of any half, on the detected returns (an undetected one's sigma is its
    # label's: :func:`_label_sigma`)
    lean = np.where(det, take(slot(lean, 0.0)), 0.0)
    sig_out = np.where(lean > 0, np.sqrt(sig_out ** 2 + lean * bin_s ** 2), sig_out)
    # the lines' doubt and step 6's are two weights of the pixel's lying on another
    # surface: the larger of the two terms, not their sum (as :func:`_line_var` takes the
    # largest of the lines that weighed a pixel)
    sig_out[..., 0] = np.where(extra > 0, np.sqrt(sig_out[..., 0] ** 2
                                                  + np.maximum(extra - added6, 0.0)),
                               sig_out[..., 0])
    return SpatialEstimate(t_out, sig_out, sig_cnt,
                           np.repeat(beta[..., None], max_returns, -1), det,
                           take(own), take(surr))


def _curvature(t_out, sig_out, det, bend, bin_s, sb, t0_s) -> None:
    """5. A surface that is not a plane. The local fit (2) is a plane: on a curved
    surface its t0 is off by the curvature its window averages, bend . (H_rr, H_rc, H_cc)
    (``bend``: the fit's weights on t0 times dr^2 / 2, dr dc, dc^2 / 2). A flat wall
    facing the sensor is one too: its range along the rays grows as 1 / cos of the angle
    off axis (an outside probe's wall at 7 m over a 40-degree field of view: 2 sigma
    covered 46-89 % of the detected pixels; docs/ranging.md "A surface that is not a
    plane"). Each detected first return's H comes from a weighted least-squares
    quadratic over the detected first returns of the (2 CURVE_R + 1)^2 around it that
    lie on its surface (within 3 pulse sigmas of a plane grown from its 3 x 3), each
    weighed by its sigma^-2; where it says the fit is off by more than ``CURVE_Z`` of
    its own sd and it fits those returns (reduced chi-square below ``CHI_MAX``: beside
    a depth step under 3 pulse sigmas both sides count as the surface, and the step
    read as a curvature moved the pixels around it, stripes 3 cm apart at (10, 2): 2
    sigma covered 48 % of their middle columns, 96 % with the test), t0 is corrected by
    it and sigma^2 gains the correction's variance less
    twice its covariance with the pixel's own error (neighbouring fits share photons:
    their errors correlate as their windows overlap, the fraction of the window they
    share). Where it does not, t0 is not corrected (the correction enters where the data
    shows it: on the project's planar scenes 0-1 % of the detected pixels), but where the
    quadratic fits (``CURVE_MIN`` returns, chi-square below ``CHI_MAX``) and
    ``CURVE_LEAN``, b^2 less its variance (its positive part) is added to the reported
    sigma^2, after the undetected returns below (2b's term for the curvature: a flat
    wall over 40 degrees at 2 signal photons, 92-93 -> 94-95 % within 2 sigma).

    Then each undetected first return (a plane's time: its own candidate's or a
    neighbour's carried over, 3b) on a surface with ``CURVE_MIN`` detected returns or
    more around it: the same quadratic's value at the pixel, over those within
    ``UNDET_TOL`` pulse sigmas of its time in its 3 x 3 and the plane grown from them,
    is reported where the two agree (within ``CURVE_Z`` sds of the two together), the
    quadratic's variance is below the pixel's, it fits its returns (reduced chi-square
    below ``CHI_MAX``) and no detected return off the surface lies within ``NEAR_OTHER``
    pulse sigmas of it (beside a surface that near, the detected returns lean towards
    it: an outside review's stripes 12 cm apart lost 5-7 points of coverage without
    the last two): the detected fits around the pixel
    average photons its one plane does not (the project's scenes, seeds 9-12, on the
    surface: the undetected pixels' RMSE 1.4-1.7 -> 1.1-1.6 cm at 2 signal photons,
    0.7-0.9 -> 0.4-0.7 cm at 5; docs/ranging.md "Undetected pixels from the detected
    ones"). Where they disagree, nothing changes. Written in place."""
    t = (t_out[..., 0] - t0_s) / bin_s
    sg = sig_out[..., 0] / bin_s
    d0 = det[..., 0] & np.isfinite(t) & np.isfinite(sg)
    if d0.sum() < CURVE_MIN:
        return
    rr, cc = np.nonzero(d0)                                   # the detected pixels
    g = np.concatenate([np.zeros((rr.size, 3)), bend[rr, cc, 0]], -1)        # (p, 6)
    b, var_b, cov0, n, _, chi = _quadratic(t, sg, d0, rr, cc, g, sb, fit=True)
    use = (n >= CURVE_MIN) & (np.abs(b) > CURVE_Z * np.sqrt(np.maximum(var_b, 0.0))) \
        & np.isfinite(b) & (chi < CHI_MAX)
    # where it does not say so, its squared estimate less its variance is a bias t0 may
    # still carry (as 2b's term: Lepski's balance), added last, to the reported sigma
    # only: the undetected returns below weigh the detected ones by their sigma as fitted
    # (a flat wall over a 40-degree field of view at 2 signal photons: its curvature
    # moves t0 by about a sigma's fifth, under CURVE_Z sds of its estimate)
    lean = (n >= CURVE_MIN) & np.isfinite(b) & (chi < CHI_MAX) & ~use & CURVE_LEAN
    rl, cl = rr[lean], cc[lean]
    bias2 = np.maximum(b[lean] ** 2 - np.maximum(var_b[lean], 0.0), 0.0)
    rr, cc = rr[use], cc[use]
    t_out[rr, cc, 0] -= b[use] * bin_s
    v = np.maximum(sg[rr, cc] ** 2 + var_b[use] - 2.0 * cov0[use], 0.25 * sg[rr, cc] ** 2)
    sig_out[rr, cc, 0] = np.sqrt(v) * bin_s
    _undetected_quadratic(t_out, sig_out, det, d0, sb, bin_s, t0_s)
    sig_out[rl, cl, 0] = np.sqrt((sig_out[rl, cl, 0] / bin_s) ** 2 + bias2) * bin_s


def _undetected_quadratic(t_out, sig_out, det, d0, sb, bin_s, t0_s) -> None:
    """:func:`_curvature`'s second part: each undetected first return from the detected
    ones (``d0``) around it, where their quadratic agrees with its plane (written in
    place)."""
    # the undetected first returns, from the detected ones as corrected above
    t = (t_out[..., 0] - t0_s) / bin_s
    sg = sig_out[..., 0] / bin_s
    rr, cc = np.nonzero(~det[..., 0] & np.isfinite(t) & np.isfinite(sg))
    if not rr.size or not UNDET_TOL:
        return
    g = np.zeros((rr.size, 6))
    g[:, 0] = 1.0
    q, var_q, _, n, near, chi = _quadratic(t, sg, d0, rr, cc, g, sb, UNDET_TOL, fit=True)
    var_q = np.maximum(var_q, 0.0)
    use = ((n >= CURVE_MIN) & (near == 0) & (chi < CHI_MAX) & np.isfinite(q)
           & (var_q < sg[rr, cc] ** 2)
           & (np.abs(t[rr, cc] - q) < CURVE_Z * np.sqrt(var_q + sg[rr, cc] ** 2)))
    rr, cc = rr[use], cc[use]
    # (sigma^2: the quadratic's variance and the two's squared difference, which a
    # surface the quadratic does not follow makes large: var_q alone covered 82-86 % of
    # the probe's sphere's undetected pixels at 2 signal photons, against 90-93 % before)
    # (never 0: noise-free returns around a pixel exactly on their quadratic)
    v = np.maximum(var_q[use] + (t[rr, cc] - q[use]) ** 2, 1e-12)
    t_out[rr, cc, 0] = q[use] * bin_s + t0_s
    sig_out[rr, cc, 0] = np.sqrt(v) * bin_s


def _off_surface(t_out, sig_out, det, sig_cnt, P0, beta, bin_s, sb, t0_s, prof=None, cand=None,
                 also=None, planes=None):
    """6. An undetected first return on a surface that is not the pixel's. Its time is a
    neighbour's surface (3b, 5); its sigma (:func:`_label_sigma`, :func:`_curvature`) is
    the error of that time on that surface. Where the pixel sees a surface its
    neighbours do not (a post a pixel wide before a wall, a grazing floor whose range
    outruns the planes), that sigma covered a third to a half of such pixels (an outside
    probe's fence and grazing floor at 2 signal photons; docs/ranging.md "An undetected
    pixel on another surface"). The pixel's own counts m in its test window at the
    reported time are the evidence: Poisson(g S + B) if it is on the surface (S the
    surface's signal a pixel, ``sig_cnt``; B its background), Poisson(B) if not. Over the
    (2 ``OFF_K`` + 1)^2 around each pixel, every reported first return's m gives a
    two-component mixture: its share pi of returns off their surface (the mean of the
    E-step's posteriors) and g, the ratio of the net counts to S over the returns the
    E-step puts on their surface (a moment step, not the likelihood's maximum: S is an
    average over pixels that include those off it, so it is low by about 1 - pi), by
    ``OFF_ITER`` steps on box sums. The pixel's posterior of being off is then
    p = expit(logit pi + g S - m log(1 + g S / B)), or the same test over the
    undetected returns of its (2 ``OFF_POOL`` + 1)^2 on its surface (:func:`_off_pool`),
    whichever is larger. Where p >= ``OFF_P``, sigma^2 gains
    max(p, ``OFF_FLOOR``) D^2, D the distance to the farthest surface the pixel may be
    on instead: the first returns reported within ``OFF_K`` pixels, and its own
    candidates ``cand`` (their times before the returns' order, and whether its window
    detects each) that its window detects or that hold ``OFF_OWN_MIN`` of its own
    photons (a candidate neither holds is mostly a peak of the window's background,
    anywhere in the histogram), and ``also`` (h, w; NaN: none), the detections
    :func:`_islands` put second, which were first returns, and ``planes`` (h, w, L; bins,
    NaN: none), the frame's planes' times at every pixel (:func:`planecut.start`'s), those
    that hold ``OFF_OWN_MIN`` of its own photons. Off its surface, a return is on one of
    those planes or elsewhere (:func:`_off_planes`): its likelihood off the surface is
    not its background's alone but the mixture's, (1 - eps) times the mean over the
    planes off its surface of its own photons' likelihood ratio there, plus eps
    (elsewhere: ratio 1), eps the share of returns off their surface that are elsewhere,
    learnt with pi by the same EM steps. That is the error of a wrong
    label weighed by its posterior, and at least enough that 2 sigma reaches it. Times,
    detections and the detected returns' sigma are untouched, and so is every return
    whose p is below
    ``OFF_P`` (the grid's scene at 2 signal photons, held-out seeds 3-4: 95-98 % of
    the undetected pixels on a surface). Written in place."""
    t = (t_out[..., 0] - t0_s) / bin_s
    ok = np.isfinite(t)
    if not OFF_P or not ok.any():
        return
    half = WIDTH_TEST * sb
    ti = np.where(ok, t, 0.0)
    m, a, z = (x[..., 0] for x in _window_counts(P0, t[..., None], half))
    B = beta * _span(a, z, prof)
    on = ok & (z > a) & (B > 0) & np.isfinite(B) & np.isfinite(sig_cnt[..., 0])
    if not on.any():
        return
    B = np.where(on, B, 1.0)
    m = np.where(on, m, 0.0)
    S = _test_signal(np.where(on, sig_cnt[..., 0], 0.0))
    w = on.astype(np.float64)
    N = np.maximum(_box(w, OFF_K), 1.0)
    pi, g, eps = np.full(t.shape, 0.1), np.ones(t.shape), np.full(t.shape, 0.5)
    alt = None if planes is None or not planes.shape[-1] or not OFF_MIX else \
        _off_planes(t, on, planes, P0, beta, half, OFF_SAME * sb, prof)

    def lam(g, eps):  # each return's log-likelihood ratio, on its surface against off it
        got = m * np.log1p(g * S / B) - g * S
        return got if alt is None else got - np.log((1.0 - eps) * alt(g * S)[0] + eps)

    def post(pi, g, eps):  # each return's posterior of being off its surface
        return np.where(on, expit(logit(pi) - lam(g, eps)), 0.0)

    for _ in range(OFF_ITER):
        r = post(pi, g, eps)
        if alt is not None:  # of the returns off their surface, the share elsewhere
            rb, has = alt(g * S)
            wa = r * w * has
            tot = _box(wa, OFF_K)
            eps = np.where(tot > 1e-9, np.clip(_box(wa * eps / ((1.0 - eps) * rb + eps), OFF_K)
                                               / np.maximum(tot, 1e-9), 1e-3, 1.0 - 1e-3), 0.5)
        pi = np.clip(_box(r, OFF_K) / N, 1e-6, 1.0 - 1e-6)
        g = np.clip(_box((1.0 - r) * (m - B) * w, OFF_K)
                    / np.maximum(_box((1.0 - r) * S * w, OFF_K), 1e-9), 0.2, 5.0)
    p = post(pi, g, eps)
    if OFF_POOL:  # and with the undetected returns around it on the same surface
        p = np.maximum(p, _off_pool(np.where(on, lam(g, eps), 0.0),
                                    np.where(on & ~det[..., 0], t, np.nan), pi, OFF_SAME * sb))
    size = 2 * OFF_K + 1
    hi = np.where(ok, t, -np.inf)
    lo = np.where(ok, t, np.inf)
    if also is not None:
        ta = (also - t0_s) / bin_s
        fa = np.isfinite(ta)
        hi, lo = np.where(fa, np.maximum(hi, ta), hi), np.where(fa, np.minimum(lo, ta), lo)
    hi = ndimage.maximum_filter(hi, size, mode="nearest")
    lo = ndimage.minimum_filter(lo, size, mode="nearest")
    D = np.where(ok, np.maximum(hi - ti, ti - lo), 0.0)
    if cand is not None:         # and the pixel's own candidates (its window's surfaces)
        tc = (cand[0] - t0_s) / bin_s
        use = np.isfinite(tc) & (cand[1] | (_window_counts(P0, tc, half)[0] >= OFF_OWN_MIN))
        D = np.maximum(D, np.where(use, np.abs(tc - ti[..., None]), 0.0).max(-1))
    if planes is not None and planes.shape[-1]:  # and the frame's planes where its photons are
        use = np.isfinite(planes) & (_window_counts(P0, planes, half)[0] >= OFF_OWN_MIN)
        D = np.maximum(D, np.where(use, np.abs(planes - ti[..., None]), 0.0).max(-1))
    sg = sig_out[..., 0] / bin_s
    sel = on & ~det[..., 0] & (p >= OFF_P) & np.isfinite(sg)
    v = sg ** 2 + np.maximum(p, OFF_FLOOR) * D ** 2
    sig_out[..., 0] = np.where(sel, np.sqrt(np.where(sel, v, 0.0)) * bin_s, sig_out[..., 0])


def _off_planes(t, on, planes, P0, beta, half, tol, prof=None):
    """6's alternatives to a return's surface (``t`` (h, w) bins; ``on``: the returns the
    test reads): the frame's planes at the pixel (``planes`` (h, w, L) bins, NaN: none)
    that lie ``tol`` bins or more from its time (off its surface: the two test windows
    do not overlap). Returns a function of the signal a pixel expects in its test window
    (h, w) that gives the mean over those planes of the pixel's own likelihood ratio
    there (its counts in its test window against its background alone; 1 where there
    is none) and whether there is one. A plane is a surface the frame holds, found from
    detections, so not a peak of the pixel's own background; each is taken as likely as
    another (the pixel's photons decide between them)."""
    tt = np.where(on[..., None] & (np.abs(planes - t[..., None]) >= tol), planes, np.nan)
    m, a, z = _window_counts(P0, tt, half)
    B = beta[..., None] * _span(a, z, prof)
    use = np.isfinite(tt) & (z > a) & (B > 0) & np.isfinite(B)
    m, B = np.where(use, m, 0.0), np.where(use, B, 1.0)
    n = use.sum(-1)

    def ratio(s):
        s = s[..., None]
        R = np.where(use, np.exp(np.minimum(m * np.log1p(s / B) - s, 700.0)), 0.0)
        return np.where(n > 0, R.sum(-1) / np.maximum(n, 1), 1.0), n > 0

    return ratio


def _off_pool(lam, tu, pi, tol):
    """6's posterior of being off the surface, tested on the pixel's undetected return
    together with those around it on the same surface: the log-likelihood ratios ``lam``
    (on against off, (h, w)) summed over the (2 ``OFF_POOL`` + 1)^2 pixels whose time
    ``tu`` (bins; NaN: detected or none) lies within ``tol`` bins of the pixel's, with
    the prior ``pi``. A label wrong over a block (a grazing floor beyond the planes'
    reach, a post's run reported on the wall) leaves each pixel a photon short, which
    one pixel's count cannot tell from chance at 2 signal photons and nine can. The
    pixel alone is :func:`_off_surface`'s own posterior; a pixel with no undetected
    return gets 0."""
    k = OFF_POOL
    h, w = tu.shape
    lp = np.pad(np.where(np.isfinite(tu), lam, 0.0), k)
    tp = np.pad(tu, k, constant_values=np.nan)
    L = np.zeros((h, w))
    with np.errstate(invalid="ignore"):
        for i in range(2 * k + 1):
            for j in range(2 * k + 1):
                L += np.where(np.abs(tp[i:i + h, j:j + w] - tu) <= tol, lp[i:i + h, j:j + w],
                              0.0)
    return np.where(np.isfinite(tu), expit(logit(pi) - L), 0.0)


def _quadratic(t, sg, d0, rr, cc, g, sb, start=3.0, fit=False):
    """:func:`_curvature`'s fit: for each pixel (rr, cc), a weighted (sigma^-2)
    least-squares quadratic in (dr, dc) over the detected (``d0``) first returns ``t``
    (bins) of the (2 CURVE_R + 1)^2 around it on its surface (within 3 pulse sigmas
    ``sb`` of a plane grown from those of its 3 x 3 within ``start`` of its own time),
    and the linear function g . p (``g`` (n, 6)) of its coefficients p (of 1, dr, dc,
    dr^2 / 2, dr dc, dc^2 / 2): its value, variance and covariance with the pixel's own
    error (the fits' errors correlate as their 7 x 7 windows overlap: rho = f(d_row)
    f(d_col), f the share of a side two windows d apart have in common); the number of
    returns it is fitted to (each (n,)); and with ``fit``, of the returns off the
    surface, the number within ``NEAR_OTHER`` pulse sigmas of the quadratic (another
    surface near it) and the reduced chi-square of its fit."""
    tol = 3.0 * sb
    h, w = t.shape
    k = CURVE_R
    d = np.arange(-k, k + 1)
    dr, dc = (x.ravel() for x in np.meshgrid(d, d, indexing="ij"))
    R, C = rr[:, None] + dr, cc[:, None] + dc
    ins = (R >= 0) & (R < h) & (C >= 0) & (C < w)
    R, C = np.clip(R, 0, h - 1), np.clip(C, 0, w - 1)
    on = d0[R, C] & ins
    tq = np.where(on, t[R, C], 0.0)
    w0 = np.where(on, 1.0 / np.maximum(sg[R, C], 1e-6) ** 2, 0.0)
    X = np.stack([np.ones(dr.size), dr, dc, dr ** 2 / 2, dr * dc, dc ** 2 / 2])  # (6, m)
    # the pixel's surface: a plane from its 3 x 3 near its time, grown
    keep = on & (np.abs(dr) <= 1) & (np.abs(dc) <= 1) \
        & (np.abs(tq - t[rr, cc, None]) < start * sb)
    for _ in range(3):
        wk = np.where(keep, w0, 0.0)
        A3 = np.einsum("pm,im,jm->pij", wk, X[:3], X[:3]) + np.eye(3) * 1e-6
        p3 = np.linalg.solve(A3, np.einsum("pm,im,pm->pi", wk, X[:3], tq)[..., None])
        keep = on & (np.abs(tq - p3[..., 0] @ X[:3]) < tol)
    wk = np.where(keep, w0, 0.0)
    A = np.einsum("pm,im,jm->pij", wk, X, X) + np.eye(6) * 1e-9
    Ai = np.linalg.inv(A)
    a = wk * ((Ai @ g[..., None])[..., 0] @ X)        # g . p = sum_q a_q t_q   (n, m)
    b = (a * tq).sum(-1)
    n = 2 * WINDOW + 1
    f = np.maximum(n - np.abs(d[:, None] - d), 0) / n             # (2k + 1, 2k + 1)
    asg = (a * np.where(keep, sg[R, C], 0.0)).reshape(-1, d.size, d.size)
    var_b = (asg * (f @ asg @ f.T)).sum((1, 2))
    cov0 = (asg * (f[k][:, None] * f[k][None, :])).sum((1, 2)) * sg[rr, cc]
    if not fit:
        return b, var_b, cov0, keep.sum(-1)
    # the detected returns around it off its surface but near it: within NEAR_OTHER
    # pulse sigmas of the quadratic
    p = (Ai @ np.einsum("pm,im,pm->pi", wk, X, tq)[..., None])[..., 0]
    res = tq - p @ X
    near = on & ~keep & (np.abs(res) < NEAR_OTHER * sb)
    chi = (wk * res ** 2).sum(-1) / np.maximum(keep.sum(-1) - 6, 1)
    return b, var_b, cov0, keep.sum(-1), near.sum(-1), chi


def _test_signal(sig_cnt):
    """The signal a pixel expects in its test window (+-``WIDTH_TEST`` pulse sigmas: 95 %
    of a Gaussian pulse) from the neighbourhood's signal a pixel, at least 0.05."""
    return 0.95 * np.maximum(sig_cnt, 0.05)


def _window_counts(P0, t, half):
    """A pixel's counts within +-``half`` bins of ``t`` (bins, (h, w, k); NaN: at 0) from
    its prefix sums ``P0``, and the window's bins [a, z)."""
    n = P0.shape[-1] - 1
    ti = np.where(np.isfinite(t), t, 0.0)
    a, z = _window_edges(ti, half, n)
    return np.take_along_axis(P0, z, -1) - np.take_along_axis(P0, a, -1), a, z


def _own_llr(P0, beta, t, sig_cnt, half, prof=None):
    """The pixel's own Poisson log-likelihood ratio of a surface at ``t`` (bins, NaN:
    none): its counts within +-``half`` against its background, with the signal a pixel
    ``sig_cnt`` (3b's score without the prior); ``t`` (h, w, k)."""
    ok = np.isfinite(t)
    m, a, z = _window_counts(P0, t, half)
    S = _test_signal(sig_cnt)
    return np.where(ok & (z > a),
                    m * np.log1p(S / np.maximum(beta[..., None] * _span(a, z, prof), 1e-9)) - S,
                    -np.inf)


OFFS = [(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1) if (i, j) != (0, 0)]  # 8 nearest


def _carried(lab, tb, slope, sig_cnt, sig_out, shifted):
    """3b's carry-over: every pixel's reported time ``tl`` (h, w) and its 8 nearest's
    reported planes carried over to it (h, w, 8): their times at the pixel, slopes,
    signal a pixel and sigma."""
    kk = lab[..., None]
    tl = np.take_along_axis(tb, kk, -1)[..., 0]
    sl = np.take_along_axis(slope, kk[..., None], 2)[:, :, 0]
    sc, sg = (np.take_along_axis(x, kk, -1)[..., 0] for x in (sig_cnt, sig_out))
    tp = np.stack([shifted(tl, i, j, np.nan) - shifted(sl[..., 0], i, j, 0.0) * i
                   - shifted(sl[..., 1], i, j, 0.0) * j for i, j in OFFS], -1)
    slp = np.stack([shifted(sl, i, j, 0.0) for i, j in OFFS], 2)
    scp = np.stack([shifted(sc, i, j, 0.0) for i, j in OFFS], -1)
    sgp = np.stack([shifted(sg, i, j, np.inf) for i, j in OFFS], -1)
    return tl, tp, slp, scp, sgp


if numba is not None:
    @numba.njit(cache=True, nogil=True)
    def _agreement_numba(tl, t, sl, tol, prior, line, diag, line_l):
        """3b's prior of each plane (t, sl) (h, w, k) at each pixel given the labels' times
        ``tl`` (h, w): ``prior`` for each of the 8 nearest on the plane (within ``tol``),
        ``line`` for each of the 2 ``line_l`` pixels of the row, column or diagonal
        (weighed ``diag``) through the pixel with most of them on it; :func:`_relabel`'s
        ``agreement`` a pixel at a time (the same operations: equal results)."""
        h, w, nk = t.shape
        out = np.empty((h, w, nk))
        for r in range(h):
            for c in range(w):
                for k in range(nk):
                    t0, a, b = t[r, c, k], sl[r, c, k, 0], sl[r, c, k, 1]
                    got = 0.0
                    for i in range(-1, 2):
                        for j in range(-1, 2):
                            if (i != 0 or j != 0) and 0 <= r + i < h and 0 <= c + j < w \
                                    and abs(tl[r + i, c + j] - (t0 + a * i + b * j)) < tol:
                                got += 1.0
                    best = 0.0
                    for di in range(4):
                        i = 0 if di == 0 else 1
                        j = 1 if di == 0 else (0 if di == 1 else (1 if di == 2 else -1))
                        run = 0.0
                        for d in range(-line_l, line_l + 1):
                            if d != 0 and 0 <= r + d * i < h and 0 <= c + d * j < w \
                                    and abs(tl[r + d * i, c + d * j]
                                            - (t0 + a * (d * i) + b * (d * j))) < tol:
                                run += 1.0
                        best = max(best, run * (diag if i != 0 and j != 0 else 1.0))
                    out[r, c, k] = prior * got + line * best
        return out


def _scores(lab, tb, llr, slope, sig_cnt, sig_out, P0, beta, half, shifted, agreement,
            prof=None):
    """3b's score of every label a pixel may take under the labels ``lab``: its slots'
    (``u`` (h, w, nc): the own log-likelihood ratio ``llr`` plus the prior) and its 8
    nearest's planes carried over (``up`` (h, w, 8), their own ratio ``lp``). Returns
    the reported times ``tl`` (h, w), ``u``, the carried planes (times ``tp``, slopes
    ``slp``, signal ``scp``, sigma ``sgp``), ``lp`` and ``up``."""
    tl, tp, slp, scp, sgp = _carried(lab, tb, slope, sig_cnt, sig_out, shifted)
    lp = _own_llr(P0, beta, tp, scp, half, prof)
    u = llr + agreement(tl, tb, slope)
    up = lp + agreement(tl, np.where(np.isfinite(tp), tp, 0.0), slp)
    return tl, u, tp, slp, scp, sgp, lp, up


def _label_sigma(state, sig_cnt, sig_out, P0, beta, bin_s, sb, prof=None) -> None:
    """sigma of an undetected pixel's reported surface (3b), in ``sig_out`` in place.
    The relabelling picks one of the pixel's labels (its candidates and its 8 nearest's
    planes carried over) by a score that is a log posterior up to a constant: the
    pixel's own Poisson log-likelihood ratio plus the Potts prior given the others'
    labels. Among the labels on the reported surface (within the prior's tolerance, 3
    sigma of the pulse, of the reported time) softmax of the scores is the conditional
    posterior p_k of each plane, and the reported time's error variance is
    sum_k p_k (sigma_k^2 + (t_k - t_reported)^2): each plane's own variance and its
    distance from the one reported. A plane carried over has its own pixel's sigma, not
    the error of its slope over the step, nor does the sigma of the pixel's own
    candidate see a neighbour's plane that disagrees: the spread of the planes does.
    The labels on other surfaces are left out: the Potts weights were chosen for the
    labelling, not as probabilities, and their softmax over every label put 7-26x the
    squared errors' sum into the variance (docs/ranging.md). Times, detections and the
    detected pixels' sigma stay as they are."""
    lab, free, tb, llr, slope, shifted, agreement = state
    if not free.any():
        return
    h, w, nc = tb.shape
    tol = 3.0 * sb
    kk = lab[..., None]
    # the 8 nearest's planes carried over, as the sweeps propose them
    tl, u, tp, _, _, sgp, _, up = _scores(lab, tb, llr, slope, sig_cnt, sig_out, P0, beta,
                                          WIDTH_TEST * sb, shifted, agreement, prof)
    t = np.concatenate([tb, tp], -1)
    u = np.concatenate([u, up], -1)
    s2 = np.concatenate([sig_out, sgp], -1) ** 2 / bin_s ** 2          # bins^2
    # the labels on the reported surface (within the prior's tolerance of its time)
    # (a plane without a sigma, inf, makes the variance inf where it has weight)
    on = np.isfinite(u) & (np.abs(t - tl[..., None]) < tol)
    top = np.max(np.where(on, u, -np.inf), -1, keepdims=True)
    # (exp of the labels on it only: another's u - top overflowed on a real capture)
    p = np.exp(np.where(on, u - np.where(np.isfinite(top), top, 0.0), -np.inf))
    tot = p.sum(-1)
    d2 = np.where(on, s2 + (np.where(on, t, 0.0) - tl[..., None]) ** 2, 0.0)
    var = np.where(p > 0, p * d2, 0.0).sum(-1) / np.where(tot > 0, tot, 1.0)
    fix = free & (tot > 0) & np.isfinite(tl)
    chosen = (np.arange(nc) == kk) & fix[..., None]
    sig_out[...] = np.where(chosen, np.sqrt(var)[..., None] * bin_s, sig_out)


def _block_move(i, j, phase, lab, before, free, tb, llr, slope, sig_cnt, sig_out, P0, beta,
                half, tol, shifted, agreement, prof=None):
    """3b's block move: every free pixel whose neighbour at (r + i, c + j) lies on another
    plane is proposed that neighbour's plane carried over, a boundary's whole run at once
    (a column for a step along a row, a row for one along a column): a straight boundary
    shifted by one pixel, which single-pixel sweeps cannot do (the line prior holds each
    of its pixels where it is). Only the columns (rows) ``phase`` modulo ``BLOCK_PHASES``
    take part, so that runs within the priors' reach of each other are few. The proposals
    are grouped by the connected parts of the pixels within that reach (3) of one, and a
    group is accepted, all of it, where the sum over its pixels of their own Poisson
    log-likelihood (the proposed pixels') plus ``BLOCK_PAIR`` times the prior of every
    pixel rises: outside a group nothing changes, so the sum is the group's exact
    change. ``before``: every pixel's prior under ``lab`` (None: not computed yet);
    returns the labels and it (None where they changed)."""
    h, w, nc = tb.shape
    kk = lab[..., None]
    tl = np.take_along_axis(tb, kk, -1)[..., 0]
    sl = np.take_along_axis(slope, kk[..., None], 2)[:, :, 0]
    tq = shifted(tl, i, j, np.nan) - shifted(sl[..., 0], i, j, 0.0) * i \
        - shifted(sl[..., 1], i, j, 0.0) * j
    mine = np.arange(w if j else h) % BLOCK_PHASES == phase
    prop = (free & (mine[None, :] if j else mine[:, None]) & np.isfinite(tq)
            & ~(np.abs(tq - tl) < tol))
    if not prop.any():
        return lab, before
    slq = np.stack([shifted(sl[..., 0], i, j, 0.0), shifted(sl[..., 1], i, j, 0.0)], -1)
    scq, sgq = (shifted(np.take_along_axis(x, kk, -1)[..., 0], i, j, v)
                for x, v in ((sig_cnt, 0.0), (sig_out, np.inf)))
    lq = _own_llr(P0, beta, np.where(prop, tq, np.nan)[..., None], scq[..., None], half,
                  prof)[..., 0]
    t2 = np.where(prop, tq, tl)
    s2 = np.where(prop[..., None], slq, sl)
    if before is None:
        before = agreement(tl, tl[..., None], sl[:, :, None])[..., 0]
    after = agreement(t2, t2[..., None], s2[:, :, None])[..., 0]
    gain = (np.where(prop, lq - np.take_along_axis(llr, kk, -1)[..., 0], 0.0)
            + BLOCK_PAIR * (after - before))
    gain = np.where(np.isfinite(gain), gain, np.where(prop, -1e9, 0.0))
    group, ng = ndimage.label(ndimage.binary_dilation(prop, np.ones((7, 7), bool)))
    take = prop & (np.bincount(group.ravel(), gain.ravel(), ng + 1)[group] > 0.0)
    if not take.any():
        return lab, before
    for arr, new in ((tb, tq), (llr, lq), (sig_cnt, scq), (sig_out, sgq)):
        arr[..., -1] = np.where(take, new, arr[..., -1])
    slope[..., -1, :] = np.where(take[..., None], slq, slope[..., -1, :])
    return np.where(take, nc - 1, lab), None


def _take_plane(r, c, pl, lab, tb, llr, slope, sig_cnt, sig_out, table, P0, beta, half,
                tol, prof=None):
    """The pixels (r, c) take the frame's planes ``pl`` (``table``: :func:`planecut.start`'s):
    their candidate on the plane, or the plane in their last slot (``tb``, ``llr``,
    ``slope``, ``sig_cnt``, ``sig_out`` written in place). ``lab`` in place."""
    T, a, S, sg = table[:4]
    nc = tb.shape[-1]
    tn = T[r, c, pl]
    dd = np.abs(tb[r, c, :-1] - tn[:, None])
    k = np.argmin(np.where(np.isfinite(dd), dd, np.inf), -1)
    have = dd[np.arange(r.size), k] < tol        # a candidate on the plane
    tt = np.full(T.shape[:2] + (1,), np.nan)
    tt[r, c, 0] = tn
    ss = np.zeros(T.shape[:2] + (1,))
    ss[r, c, 0] = S[pl]
    lp = _own_llr(P0, beta, tt, ss, half, prof)[r, c, 0]
    new = np.where(have, llr[r, c, k], lp)
    ok = np.isfinite(new)      # (not a plane whose pulse lies mostly outside the window)
    lab[r[ok & have], c[ok & have]] = k[ok & have]
    put = ok & ~have                              # else the plane in the last slot
    rp, cp, pp = r[put], c[put], pl[put]
    tb[rp, cp, -1] = tn[put]
    llr[rp, cp, -1] = lp[put]
    sig_cnt[rp, cp, -1] = S[pp]
    sig_out[rp, cp, -1] = sg[pp]
    slope[rp, cp, -1, :] = a[pp, 1:]
    lab[rp, cp] = nc - 1


def _plane_of(lab, tb, T, tol):
    """Every pixel's plane among the frame's: the one its reported time lies on (-1: none)."""
    tl = np.take_along_axis(tb, lab[..., None], -1)[..., 0]
    d = np.abs(T - tl[..., None])
    d = np.where(np.isfinite(d), d, np.inf)
    cat = np.argmin(d, -1)
    return np.where(np.take_along_axis(d, cat[..., None], -1)[..., 0] < tol, cat, -1)


def _edges(lab, free, det, tb, llr, slope, sig_cnt, sig_out, table, P0, beta, half, tol,
           prof=None, compiled=None, threads=1):
    """3b's last step, edges. The sweeps' priors count the pixels along rows, columns and
    diagonals, and every monotone staircase between two points has the same length on
    the pixel grid: beside an edge at 30 degrees a run of pixels one pixel over costs
    them nothing, and the run's own few photons hardly decide. The edge's pixels further
    along do. Each undetected pixel beside a boundary between two of the frame's planes
    (its own, A, and the commonest other among its 8 nearest, B) goes to B where
    :func:`planecut.edge_side` gives B's side a posterior above ``EDGE_P``: in the 11 x 11
    window around it, where its labels are one straight boundary, every line (36
    directions, every offset) weighed by the likelihood of the window's photons; near a
    corner or a run of wrong labels, the windows beside it. Up to three passes (until
    none moves), each on the pixels the one before's moves reach. Detection is
    untouched. (Seeds 1-8 at (2, 50), pixels > 10 cm off, against the corners' step it
    replaced: the grid's scene 24 -> 19, turned by 30 degrees 276 -> 158; held out,
    seeds 9-15: 37 -> 27 and 250 -> 118; docs/ranging.md "Edges".) Returns the labels
    and the detections the lines doubt (:class:`_Doubts`; each such pixel takes
    the line's plane as its label); ``tb``, ``llr``, ``slope``, ``sig_cnt`` and
    ``sig_out`` are written in place where a plane is put in a pixel's last slot."""
    T, lp = table[0], table[4]
    weight = np.where(free, planecut.EDGE_FREE, 1.0)
    dets = det.any(-1)
    near = np.ones(free.shape, bool)  # after a pass: the pixels its moves' windows reach
    for _ in range(planecut.EDGE_PASSES):
        cat = _plane_of(lab, tb, T, tol)
        edge = ndimage.maximum_filter(cat, 3) != ndimage.minimum_filter(cat, 3)
        who = np.argwhere(free & edge & (cat >= 0) & near)
        if not who.size:
            break
        A = cat[who[:, 0], who[:, 1]]
        B = _commonest_other(cat, weight, who, A, 1)
        who, A, B = who[B >= 0], A[B >= 0], B[B >= 0]   # (beside no other plane: none)
        post = planecut.edge_side(cat, weight, dets, lp, who, A, B, compiled, threads)
        move = post > planecut.EDGE_P
        r, c, pl = who[move, 0], who[move, 1], B[move]
        if not r.size:
            break
        _take_plane(r, c, pl, lab, tb, llr, slope, sig_cnt, sig_out, table, P0, beta,
                    half, tol, prof)
        moved = np.zeros(free.shape, bool)
        moved[r, c] = True
        near = ndimage.maximum_filter(moved, 2 * (planecut.EDGE_R + planecut.EDGE_SHIFT) + 1)
    doubted = _no_doubt(free.shape)
    if EDGE_LINES:   # and the edges as whole lines (stages/ranging/edgelines.py)
        # (the sky's labels are its neighbours': no plane for the lines)
        sky = _no_surface(P0, beta, T, half, free, dets, prof) if LINE_SKY else None
        w = free.shape[1]
        before = []      # the earlier passes' posteriors (edgelines.LineMoves' seen_*)
        for k in range(LINE_PASSES):
            cat = _plane_of(lab, tb, T, tol)
            if sky is not None:
                cat = np.where(sky, -1, cat)
            got = edgelines.line_moves(cat, weight, dets, lp, planecut.EDGE_CAP,
                                       edgelines.LINE_DET)
            q, pl, qd, pld, p_was = got[:5]
            if q.size:
                _take_plane(q // w, q % w, pl, lab, tb, llr, slope, sig_cnt, sig_out, table,
                            P0, beta, half, tol, prof)
            if not q.size or k == LINE_PASSES - 1:
                break    # (no move: a pass again would find the same lines)
            before.append(got[5:])
        # a detection the line doubts, where the two planes' test windows at the pixel
        # do not overlap (else the detection holds the other plane's photons: one
        # surface, curved, that two planes share; a sphere at (10, 2))
        rd, cd = qd // w, qd % w
        keep = (np.abs(tb[rd, cd, lab[rd, cd]] - T[rd, cd, pld]) > 2 * half) & EDGE_DOUBT
        qd, pld, p_was, rd, cd = qd[keep], pld[keep], p_was[keep], rd[keep], cd[keep]
        if qd.size:
            # the pixel takes the line's plane, and the chance it is where its
            # detection put it stays in its sigma (_finish)
            doubted.doubted[rd, cd] = True
            doubted.p_was[rd, cd] = p_was
            doubted.t_was[rd, cd] = tb[rd, cd, lab[rd, cd]]
            _take_plane(rd, cd, pld, lab, tb, llr, slope, sig_cnt, sig_out, table, P0, beta,
                        half, tol, prof)
        if EDGE_SIGMA:
            doubted.line_var[...] = _line_var(*_passes_seen(before, got[5:]),
                                              _plane_of(lab, tb, T, tol), T)
    return lab, doubted


def _islands(lab, det, seen, tb, llr, slope, sig_cnt, sig_out, P0, beta, half, tol, p_fa,
             shifted, agreement, doubted, prof=None) -> None:
    """A detection no neighbour holds: the pixel's own photons detect a surface (at
    ``p_fa``) on whose plane none of its 8 nearest lies (neither its label nor any
    surface it detects, ``seen``), whose time the 8 nearest's photons do not hold
    (summed, at ``NONE_P``: a pane each sees with a photon or so) nor the two on either
    side of it along its row, column or a diagonal (at ``NONE_P``: a post a pixel wide),
    and which its own counts there do not detect at the frame's level (``p_fa`` over
    the frame's pixels, as step 1's lone candidates). It is weighed as an undetected
    pixel's label is (3b's score: its own Poisson likelihood plus the prior of the
    labels around it), over its candidates and its 8 nearest's planes carried over;
    where another plane scores higher, the pixel takes that plane as its label, which
    :func:`_finish` reports first, the chance the detection's surface is the pixel's
    (the two scores' logistic) in its sigma. The detection stays, a further return: the
    score weighs one surface a pixel against another, not whether a second is there,
    which the pixel's own test at ``p_fa`` decided. (The photons are taken at the
    detection's time, flat: an island's plane is fitted from neighbours that hardly
    hold it, and its slope carried the window about a post onto the wall behind.)
    ``lab``, ``tb``, ``llr``, ``slope``, ``sig_cnt``, ``sig_out`` and ``doubted`` are
    written in place."""
    h, w, nc = tb.shape
    dets = det.any(-1) & ~doubted.doubted
    if not dets.any():
        return
    tl = np.take_along_axis(tb, lab[..., None], -1)[..., 0]
    kk = lab[..., None]
    sl = np.take_along_axis(slope, kk[..., None], 2)[:, :, 0]
    # an 8 nearest on the detection's plane: its label, or any surface it detects (a
    # pane before a wall: each pixel's label the wall, its second return the pane)
    tn = np.concatenate([tl[..., None], np.where(seen, tb, np.nan)], -1)
    held = np.zeros((h, w), bool)
    for i, j in OFFS:
        pred = tl + sl[..., 0] * i + sl[..., 1] * j
        held |= (np.abs(shifted(tn, i, j, np.nan) - pred[..., None]) < tol).any(-1)
    who = dets & ~held
    if not who.any():
        return

    def counts(i, j):  # the counts of each pixel's neighbour (i, j) about the pixel's
        # time, and those due (the pixel's time put at the neighbour, then brought back)
        t = (shifted(tl, -i, -j, np.nan) if i or j else tl)[..., None]
        m, a, z = _window_counts(P0, t, half)
        ok = np.isfinite(t[..., 0])
        m = np.where(ok, m[..., 0], 0.0)
        b = np.where(ok, beta * _span(a[..., 0], z[..., 0], prof), 0.0)
        return (shifted(m, i, j, 0.0), shifted(b, i, j, 0.0)) if i or j else (m, b)

    # its own counts about the reported time are no detection at the frame's level
    who &= poisson_tail(*counts(0, 0)) > p_fa / (h * w)
    # nor do the 8 nearest's photons about that time stand out (a second surface each of
    # them sees with a photon or so, as a pane, and detects rarely): their counts in
    # the test window, summed, no detection at ``NONE_P`` against their background
    got = {(i, j): counts(i, j) for i, j in OFFS}
    who &= poisson_tail(sum(x[0] for x in got.values()),
                        sum(x[1] for x in got.values())) > NONE_P
    # nor the two on either side of it along its row, column or a diagonal (a post or
    # a wire a pixel wide, whose pixels the relabelling gives the wall behind; further
    # along, a line reaches the surface beyond an edge two pixels away)
    for i, j in ((0, 1), (1, 0), (1, 1), (1, -1)):
        (m1, b1), (m2, b2) = got[i, j], got[-i, -j]
        who &= poisson_tail(m1 + m2, b1 + b2) > NONE_P
    if not who.any():
        return
    _, u, tp, slp, scp, sgp, lp, up = _scores(lab, tb, llr, slope, sig_cnt, sig_out, P0,
                                              beta, half, shifted, agreement, prof)
    u_was = np.take_along_axis(u, kk, -1)[..., 0]
    u_slot = np.where(np.arange(nc) == kk, -np.inf, u)
    k_slot = np.argmax(u_slot, -1)
    k_car = np.argmax(up, -1)
    b_slot = np.take_along_axis(u_slot, k_slot[..., None], -1)[..., 0]
    b_car = np.take_along_axis(up, k_car[..., None], -1)[..., 0]
    move = who & (np.maximum(b_slot, b_car) > u_was)
    r, c = np.nonzero(move)
    if not r.size:
        return
    car = b_car[r, c] > b_slot[r, c]
    doubted.island[r, c] = True
    doubted.p_was[r, c] = expit(u_was[r, c] - np.maximum(b_slot[r, c], b_car[r, c]))
    doubted.t_was[r, c] = tl[r, c]
    lab[r, c] = np.where(car, nc - 1, k_slot[r, c])
    rc, cc, k = r[car], c[car], k_car[r[car], c[car]]
    tb[rc, cc, -1], llr[rc, cc, -1] = tp[rc, cc, k], lp[rc, cc, k]
    sig_cnt[rc, cc, -1], sig_out[rc, cc, -1] = scp[rc, cc, k], sgp[rc, cc, k]
    slope[rc, cc, -1, :] = slp[rc, cc, k]


def _no_surface(P0, beta, T, half, free, dets, prof=None):
    """The undetected pixels that see no surface, for the lines (``LINE_SKY``): those
    around which (the (2 ``NONE_K`` + 1)^2 window) no plane of the frame (``T`` (h, w,
    L), bins) holds photons: each plane's counts in the test window about its time,
    summed over the window, are no detection against their background at ``NONE_P``
    (the exact Poisson tail; 0.023, two sds' one-sided tail)
    (a dark surface's few photons a pixel, summed over 25, stand out; a test of each
    pixel against the plane's signal, the sweeps' ratio, took an 8-pixel square at a
    quarter of the light for sky). And beside which (3 x 3) no pixel is detected
    (``dets``), less what no 3 x 3 of such pixels covers (a binary opening): the sky is
    a region, a surface's few such pixels are not, and one in an edge cuts its run."""
    if not T.shape[-1]:
        return np.zeros(free.shape, bool)
    ok = np.isfinite(T)
    m, a, z = _window_counts(P0, T, half)
    b = beta[..., None] * _span(a, z, prof)
    m, b = np.where(ok, m, 0.0), np.where(ok, b, 0.0)
    held = poisson_tail(_box(m, NONE_K), _box(b, NONE_K)) <= NONE_P   # (the exact tail)
    none = free & ~held.any(-1) & ~ndimage.maximum_filter(dets, 3)
    return ndimage.binary_opening(none, np.ones((3, 3), bool)) if NONE_OPEN else none


def _passes_seen(before, last):
    """The posteriors the lines' passes weighed each undetected pixel with (``seen_q``,
    ``seen_a``, ``seen_b``, ``seen_p_a`` of :class:`edgelines.LineMoves`, the earlier
    passes' in ``before``): a pixel's from the last pass that weighed it (an earlier
    pass's lines, cut short or tilted by the labels it corrected, are the worse
    judges; a pixel only they weighed keeps their doubt)."""
    out = [np.asarray(x) for x in last]
    for rec in reversed(before):
        new = ~np.isin(rec[0], out[0])
        out = [np.concatenate([o, np.asarray(x)[new]]) for o, x in zip(out, rec, strict=True)]
    return out


def _line_var(q, A, B, p_a, cat, T):
    """The variance (bins^2) the lines' posteriors leave in each pixel they weighed
    (pixels ``q``, pairs of planes ``A``, ``B``, posterior of A's side ``p_a``: from
    :class:`edgelines.LineMoves`), once the moves are made: the posterior
    that the pixel lies on the other plane of the pair, times the squared distance
    between the two planes' times at it; where several lines or corners weighed it,
    the largest. Only where that posterior is ``EDGE_SIGMA_P`` (5 %) or more: a 2-sigma
    interval holds 95 % without reaching a plane of less, and the lines' far tails
    (1e-6 of a plane 3 m off: 0.3 cm of sigma) widened 7 % of the undetected pixels by
    over a centimetre on seeds 1-3 of the grid's scene at (2, 50). A pixel whose label
    is on neither plane of a pair (another step moved it) takes nothing from that pair."""
    h, w = cat.shape
    out = np.zeros((h, w))
    if not q.size:
        return out
    r, c = q // w, q % w
    fin = cat[r, c]
    on = (fin == A) | (fin == B)
    p_other = np.where(fin == A, 1.0 - p_a, p_a)
    with np.errstate(invalid="ignore"):
        d2 = (T[r, c, A] - T[r, c, B]) ** 2
    ok = on & np.isfinite(d2) & np.isfinite(p_other) & (p_other >= EDGE_SIGMA_P)
    v = np.where(ok, p_other, 0.0) * np.where(ok, d2, 0.0)
    np.maximum.at(out.reshape(-1), q, v)
    return out


class _Doubts(NamedTuple):
    """What :func:`_edges`' lines leave in doubt, per pixel: whether its detection is
    doubted, the posterior that it lies where it was detected and the time it was
    detected at; the variance the lines leave in an undetected pixel's label
    (bins^2, :func:`_line_var`); and whether its detection is an island that
    :func:`_islands` put after its label (``p_was`` and ``t_was`` its own)."""

    doubted: np.ndarray
    p_was: np.ndarray
    t_was: np.ndarray
    line_var: np.ndarray
    island: np.ndarray


def _no_doubt(shape) -> _Doubts:
    """No doubts yet (:class:`_Doubts` of zeros)."""
    return _Doubts(np.zeros(shape, bool), np.zeros(shape), np.zeros(shape), np.zeros(shape),
                   np.zeros(shape, bool))


def _commonest_other(cat, weight, who, A, k):
    """The commonest label other than A (and none) within k of each pixel of ``who``,
    by weight (-1: none)."""
    h, w = cat.shape
    L = int(cat.max()) + 1
    n = who.shape[0]
    if L <= 0:
        return np.full(n, -1)
    di, dj = np.mgrid[-k:k + 1, -k:k + 1]
    r, c = who[:, 0, None] + di.ravel(), who[:, 1, None] + dj.ravel()
    ins = (r >= 0) & (r < h) & (c >= 0) & (c < w)
    cc = np.where(ins, cat[np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)], -1)
    ww = np.where(ins, weight[np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)], 0.0)
    ok = (cc >= 0) & (cc != A[:, None])
    hist = np.zeros((n, L))
    np.add.at(hist, (np.nonzero(ok)[0], cc[ok]), ww[ok])
    return np.where(hist.max(-1) > 0, np.argmax(hist, -1), -1)


def _relabel(t_out, sig_out, slope, mine, bw, sig_cnt, rank, det, P0, beta, bin_s, sb,
             t0_s, prof=None, compiled=None, seen=None, threads=1, p_fa=None):
    """3b. Which candidate an undetected pixel reports: the one that maximises the pixel's
    own Poisson log-likelihood ratio (its counts in the test window against its
    background, the signal per pixel the neighbourhood saw) plus ``PRIOR`` for each of
    its 8 nearest whose reported time lies on the candidate's plane (within 3 sigma):
    a few ICM sweeps of a Potts MRF, at a constant cost a pixel. The detected pixels
    (``det``: those the pixel's own photons detect, :func:`_finish`) keep their surfaces
    (and anchor their neighbours); ``seen``: every detection, which the cut's planes are
    found from (default ``det``). Every
    distinct candidate takes part, also one its window does not detect: a surface that is
    a minority of the window, at an edge, is often one (2 signal and 50 background
    photons, seed 1, without what follows: 88 surface pixels > 10 cm off against 127 with
    the detected ones only). And, as PatchMatch propagates, each
    of the 8 nearest's reported plane carried over to the pixel (its last slot, written
    in place with its sigma and signal): a steep surface's plane fitted from one side
    of an edge misses the pixel by more than a pulse, its neighbour's does not. Returns
    the ranking with the chosen candidate of every undetected pixel first. (Seed 1, (2,
    50), 5 sweeps: 21 pixels > 10 cm off at PRIOR 0.7; 35 at 0.5; 29 at 1.0 and 3 sweeps.)
    And a straight-boundary prior: ``LINE`` for each of the ``2 LINE_L`` pixels of the
    row, column or diagonal (at ``DIAG``) through the pixel that lie most on the plane.
    Beside a straight edge the 8 nearest split 5 to 3 for the pixel's surface (4 to 4
    where two pixels along the edge are wrong together: an ICM fixed point), and one
    background photon in a wrong candidate's window outweighs that; the line along the
    edge is all on the pixel's surface (seed 1, (2, 50): 21 -> 1 pixel > 10 cm off;
    docs/ranging.md). Then :func:`_block_move` for each direction along a row or a
    column: a boundary's run shifted by one pixel at once (seed 1 at (2, 10): 6 -> 3
    pixels > 10 cm off, (2, 2): 4 -> 2; (2, 50): 1 -> 1). The sweeps start from
    :func:`planecut.start`'s labels, not each pixel's own best candidate: an undetected
    pixel on its candidate on its label's plane, or on the plane in the last slot (seeds
    1-15 at (2, 50): 188 -> 100 pixels > 10 cm off, turned by 30 degrees 789 -> 602;
    docs/ranging.md "Where the sweeps start"). Last, :func:`_edges` (which needs the
    cut's planes), then :func:`_islands` (given ``p_fa``)."""
    h, w, nc = t_out.shape
    tb = (t_out - t0_s) / bin_s                               # bins
    S = _test_signal(sig_cnt)
    llr = np.where(np.isfinite(tb), mine * np.log1p(S / np.maximum(bw, 1e-9)) - S, -np.inf)
    lab = np.argmax(np.where(det, 1e12, 0.0) + rank, axis=-1)
    free = ~det.any(-1)
    tol = 3.0 * sb
    half = WIDTH_TEST * sb
    # the sweeps start from the frame's planes by a graph cut (stages/ranging/planecut.py):
    # a candidate on the pixel's plane, or the plane itself in the last slot
    # (the frame's planes from ``seen``, every detection, where given: the corner
    # windows' detections, which do not fix their pixels' labels, still find planes)
    got = planecut.start(tb, slope, det, sig_cnt, sig_out, P0, beta, sb, prof, seen,
                         threads)
    if got is not None:
        plane, table = got
        r, c = np.nonzero(free & (plane >= 0))
        _take_plane(r, c, plane[r, c], lab, tb, llr, slope, sig_cnt, sig_out, table, P0,
                    beta, half, tol, prof)

    def shifted(x, i, j, v):  # x at the neighbour (r + i, c + j), v outside the image
        # (slices, not np.pad: its per-call cost was a third of a 1 x 128 line's ranging)
        out = np.full(x.shape, v, x.dtype)
        if abs(i) >= h or abs(j) >= w:  # (the neighbour is off the image everywhere)
            return out
        out[max(-i, 0):h - max(i, 0), max(-j, 0):w - max(j, 0)] = \
            x[max(i, 0):h - max(-i, 0), max(j, 0):w - max(-j, 0)]
        return out

    def agreement(tl, t, sl):  # the prior of the plane (t, sl): its 8 nearest and line
        if compiled:
            return _agreement_numba(
                np.ascontiguousarray(tl, np.float64), np.ascontiguousarray(t, np.float64),
                np.ascontiguousarray(sl, np.float64), float(tol), float(PRIOR), float(LINE),
                float(DIAG), int(LINE_L))
        on = {}  # whether the neighbour at (i, j) lies on the plane

        def lies(i, j):
            if (i, j) not in on:
                pred = t + sl[..., 0] * i + sl[..., 1] * j
                on[i, j] = np.abs(shifted(tl, i, j, np.nan)[..., None] - pred) < tol
            return on[i, j]

        got = np.zeros(t.shape)
        for i, j in OFFS:
            got += lies(i, j)
        # the straight boundary: the row, column or diagonal through the pixel along
        # which most of the 2 LINE_L pixels lie on the plane
        best = np.zeros(t.shape)
        for i, j in ((0, 1), (1, 0), (1, 1), (1, -1)):
            run = np.zeros(t.shape)
            for d in [x for x in range(-LINE_L, LINE_L + 1) if x]:
                run += lies(d * i, d * j)
            best = np.maximum(best, run * (DIAG if i and j else 1.0))
        return PRIOR * got + LINE * best

    for _ in range(SWEEPS):
        tl = np.take_along_axis(tb, lab[..., None], -1)[..., 0]
        u = llr + agreement(tl, tb, slope)
        lab = np.where(free, np.argmax(u, -1), lab)
        # the 8 nearest's planes carried over: the best replaces the pixel's last slot
        tl, tp, slp, scp, sgp = _carried(lab, tb, slope, sig_cnt, sig_out, shifted)
        lp = _own_llr(P0, beta, tp, scp, half, prof)
        ti = np.where(np.isfinite(tp), tp, 0.0)
        up = lp + agreement(tl, ti, slp)
        k = np.argmax(up, -1)
        best = np.take_along_axis(up, k[..., None], -1)[..., 0]
        mine_now = np.take_along_axis(u, lab[..., None], -1)[..., 0]
        take = free & (best > mine_now)
        kk = k[..., None]
        for arr, new in ((tb, tp), (llr, lp), (sig_cnt, scp), (sig_out, sgp)):
            arr[..., -1] = np.where(take, np.take_along_axis(new, kk, -1)[..., 0],
                                    arr[..., -1])
        slope[..., -1, :] = np.where(take[..., None],
                                     np.take_along_axis(slp, kk[..., None], 2)[:, :, 0],
                                     slope[..., -1, :])
        lab = np.where(take, nc - 1, lab)
    before = None  # every pixel's prior under lab, while no block has moved
    for _ in range(BLOCK_ROUNDS):
        for (i, j), phase in product(((0, 1), (0, -1), (1, 0), (-1, 0)),
                                     range(BLOCK_PHASES)):
            lab, before = _block_move(i, j, phase, lab, before, free, tb, llr, slope,
                                      sig_cnt, sig_out, P0, beta, half, tol, shifted,
                                      agreement, prof)
    doubted = _no_doubt(free.shape)
    if got is not None:
        lab, doubted = _edges(lab, free, det, tb, llr, slope, sig_cnt, sig_out, table, P0,
                              beta, half, tol, prof, compiled, threads)
    if ISLAND and p_fa is not None:
        _islands(lab, det, det if seen is None else seen, tb, llr, slope, sig_cnt, sig_out,
                 P0, beta, half, tol, p_fa, shifted, agreement, doubted, prof)
    t_out[..., -1] = tb[..., -1] * bin_s + t0_s
    chosen = np.arange(nc) == lab[..., None]
    free = free | doubted.doubted | doubted.island
    return (np.where(free[..., None] & chosen, 1e11, 0.0) + rank,
            (lab, free, tb, llr, slope, shifted, agreement, doubted,
             None if got is None else table[0]))
