"""Scenes and photon histograms for the spatial ranging benchmark and tests, written apart
from the project's simulator (numpy only, nothing of ``stages``): Lindell 2018's set-up,
64 x 64 pixels, 1024 bins of 80 ps, a Gaussian pulse of 440 ps FWHM, signal and
background photons per pixel as given (Poisson), the background flat over the bins.

The scene is piecewise planar: a wall slanted left to right (6-8 m), a floor slanted
top to bottom in the lower rows (3-4 m), a box facing the sensor (3 m) and a slanted
board (4-5.5 m) with depth edges all round, a semi-transparent pane (3.6 m) in front of
the wall where each pixel sees two surfaces, half the signal each, and empty sky (no
return at all) in the upper left and a gap of sky beside the box.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

C = 299_792_458.0
BIN_S = 80e-12
N_BINS = 1024
PULSE_FWHM_S = 440e-12
SIGMA_S = PULSE_FWHM_S / (2 * np.sqrt(2 * np.log(2)))


@dataclass(frozen=True)
class Scene:
    """``depth`` (H, W, 2) metres of up to two surfaces a pixel (NaN: none) and
    ``share`` (H, W, 2) the signal's split between them."""

    depth: np.ndarray
    share: np.ndarray

    @property
    def surface(self) -> np.ndarray:
        return np.isfinite(self.depth[..., 0])


# Every edge of the scene, in units of the image's height (r, down) and width (c, across):
# the box's right edge is the sky gap's left one. benchmarks/spatial_oracle.py moves them.
EDGES = {
    "floor_r": 0.75,
    "box_r0": 0.3, "box_r1": 0.65, "box_c0": 0.12, "box_c1": 0.4,
    "gap_r0": 0.3, "gap_r1": 0.65, "gap_c1": 0.5,
    "board_r0": 0.2, "board_r1": 0.7, "board_c0": 0.55, "board_c1": 0.8,
    "sky_r1": 0.25, "sky_c1": 0.45,
    "pane_r0": 0.72, "pane_r1": 0.95, "pane_c0": 0.82, "pane_c1": 0.97,
    "pane2_r0": 0.05, "pane2_r1": 0.18, "pane2_c0": 0.6, "pane2_c1": 0.9,
}


def scene(h: int = 64, w: int = 64, angle_deg: float = 0.0, edges: dict | None = None
          ) -> Scene:
    """``angle_deg``: the scene turned about the image's centre (its edges then lie
    along no row, column or diagonal; the corners turned out of the image are lost).
    ``edges``: some of :data:`EDGES` moved (the rest as they are)."""
    e = {**EDGES, **(edges or {})}
    unknown = set(e) - set(EDGES)
    if unknown:
        raise ValueError(f"no such edge: {sorted(unknown)}; the edges: {sorted(EDGES)}")
    r, c = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]  # 0..1 down and across
    if angle_deg:
        a = np.deg2rad(angle_deg)
        r, c = (0.5 + (r - 0.5) * np.cos(a) - (c - 0.5) * np.sin(a),
                0.5 + (r - 0.5) * np.sin(a) + (c - 0.5) * np.cos(a))
    d = 6.0 + 2.0 * c                                   # the wall, slanted
    floor = r > e["floor_r"]
    d = np.where(floor, 3.0 + 1.0 * (1 - r) / 0.25, d)  # the floor, nearer at the bottom
    box = (r > e["box_r0"]) & (r < e["box_r1"]) & (c > e["box_c0"]) & (c < e["box_c1"])
    d = np.where(box, 3.0, d)
    board = ((r > e["board_r0"]) & (r < e["board_r1"])
             & (c > e["board_c0"]) & (c < e["board_c1"]))
    d = np.where(board, 4.0 + 1.5 * (c - 0.55) / 0.25 + 0.5 * (r - 0.2), d)
    sky = (((r < e["sky_r1"]) & (c < e["sky_c1"]))
           | ((r > e["gap_r0"]) & (r < e["gap_r1"]) & (c >= e["box_c1"]) & (c < e["gap_c1"])))
    d = np.where(sky, np.nan, d)
    pane = ((r > e["pane_r0"]) & (r < e["pane_r1"])
            & (c > e["pane_c0"]) & (c < e["pane_c1"]) & ~floor)
    pane |= ((r > e["pane2_r0"]) & (r < e["pane2_r1"])
             & (c > e["pane2_c0"]) & (c < e["pane2_c1"]))
    depth = np.stack([d, np.where(pane, 3.6, np.nan)], -1)
    share = np.stack([np.where(pane, 0.5, 1.0), np.where(pane, 0.5, 0.0)], -1)
    return Scene(depth, share)


def histograms(sc: Scene, signal: float, background: float, rng) -> np.ndarray:
    """Photon counts (H, W, N_BINS): Poisson(signal x share) photons a surface at
    2 depth / c with the Gaussian pulse, Poisson(background) photons flat over the bins."""
    rng = np.random.default_rng(rng)
    h, w, _ = sc.depth.shape
    out = np.zeros(h * w * N_BINS, np.int64)
    pix = np.arange(h * w)
    for k in range(2):
        d = sc.depth[..., k].ravel()
        lam = np.where(np.isfinite(d), signal * sc.share[..., k].ravel(), 0.0)
        n = rng.poisson(lam)
        who = np.repeat(pix, n)
        t = 2 * np.repeat(np.nan_to_num(d), n) / C + rng.normal(0, SIGMA_S, who.size)
        b = np.floor(t / BIN_S).astype(np.int64)
        ok = (b >= 0) & (b < N_BINS)
        np.add.at(out, who[ok] * N_BINS + b[ok], 1)
    nb = rng.poisson(background, h * w)
    who = np.repeat(pix, nb)
    np.add.at(out, who * N_BINS + rng.integers(0, N_BINS, who.size), 1)
    return out.reshape(h, w, N_BINS)


def depth_errors(sc: Scene, depth_m: np.ndarray) -> np.ndarray:
    """|estimate - nearest true surface| on the pixels that have a surface (metres)."""
    e = np.abs(depth_m[..., None] - sc.depth)
    return np.fmin(e[..., 0], e[..., 1])[sc.surface]  # (NaN only where neither is a surface)


def window_errors(sc: Scene, depth_m: np.ndarray) -> np.ndarray:
    """:func:`depth_errors` of an estimate whose missing (NaN) or out-of-window depths
    are put at the window's nearer end (a pixel reported at no depth is off by its
    whole range): every spatial benchmark's and test's error."""
    window_m = N_BINS * BIN_S * C / 2
    return depth_errors(sc, np.clip(np.nan_to_num(depth_m, nan=0.0), 0.0, window_m))
