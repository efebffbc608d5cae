"""An outside probe's scenes and photons for the spatial estimator
(:mod:`benchmarks.spatial_probe`), written apart from :mod:`benchmarks.spatial_scenes`
(which the estimator was tuned on) by a session that had not seen the estimator's code:
ranges along each pixel's ray over a 40-degree field of view (so a flat wall facing the
sensor is curved in pixel coordinates), spheres, cylinders, a grazing floor, thin posts
and wires, edges at 12 and 45 degrees, an acute triangle, mostly sky, backgrounds not
flat in time, mixed pixels.

Depth maps are ranges (m) along each pixel's ray; NaN = sky. A scene function takes
continuous pixel coordinates (r, c) (pixel (i, j) spans [i, i+1) x [j, j+1)) and the
frame shape, and returns the range. ``ss`` > 1 draws each photon's sub-pixel position
uniformly within the pixel (mixed pixels at edges); ss = 1 uses the pixel centre.
"""
from __future__ import annotations

import numpy as np

C = 299_792_458.0
BIN_S = 80e-12
N_BINS = 1024
SIGMA_S = 440e-12 / (2 * np.sqrt(2 * np.log(2)))
FOV_DEG = 40.0


def rays(r, c, h, w, fov_deg=FOV_DEG):
    """Unit ray directions (x right, y down, z forward), the same angular pitch in both
    axes: fov_deg spans the larger of h, w."""
    p = np.tan(np.deg2rad(fov_deg / 2)) / (max(h, w) / 2)
    x = (c - w / 2) * p
    y = (r - h / 2) * p
    n = np.sqrt(x * x + y * y + 1)
    return x / n, y / n, 1 / n


def plane_range(dx, dy, dz, n, d0):
    """Range to plane n . p = d0 along (dx, dy, dz) (NaN if behind / parallel)."""
    den = n[0] * dx + n[1] * dy + n[2] * dz
    with np.errstate(divide="ignore", invalid="ignore"):
        t = d0 / den
    return np.where(t > 0, t, np.nan)


def sphere_range(dx, dy, dz, ctr, rad):
    b = dx * ctr[0] + dy * ctr[1] + dz * ctr[2]
    cc = ctr[0] ** 2 + ctr[1] ** 2 + ctr[2] ** 2 - rad ** 2
    disc = b * b - cc
    with np.errstate(invalid="ignore"):
        t = b - np.sqrt(disc)
    return np.where(disc >= 0, t, np.nan)


def cyl_range(dx, dy, dz, x0, z0, rad):
    """Vertical (y) cylinder axis at (x0, z0)."""
    a = dx * dx + dz * dz
    b = dx * x0 + dz * z0
    cc = x0 * x0 + z0 * z0 - rad * rad
    disc = b * b - a * cc
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (b - np.sqrt(disc)) / a
    return np.where(disc >= 0, t, np.nan)


def nearest(*ts):
    out = np.full(np.shape(ts[0]), np.nan)
    for t in ts:
        out = np.fmin(out, t)
    return out


def slanted_wall(dx, dy, dz, dist=7.0, yaw_deg=20.0):
    a = np.deg2rad(yaw_deg)
    return plane_range(dx, dy, dz, (np.sin(a), 0.0, np.cos(a)), dist)


# ---------------------------------------------------------------- scenes
def sc_sphere(r, c, h, w):
    d = rays(r, c, h, w)
    return nearest(sphere_range(*d, (-0.3, 0.1, 4.0), 1.0), slanted_wall(*d, 7.0, 20.0))


def sc_cylinder(r, c, h, w):
    d = rays(r, c, h, w)
    return nearest(cyl_range(*d, 0.4, 3.5, 0.6), slanted_wall(*d, 6.0, -10.0))


def sc_steep(r, c, h, w):
    """Depth 10 cm more per pixel across the columns (2.5 .. 8.9 m)."""
    return 2.5 + 0.10 * c + 0 * r


def sc_steep_diag(r, c, h, w):
    """10 cm per pixel along the diagonal (7 cm per row and per column)."""
    return 2.5 + 0.0707 * (r + c)


def sc_grazing(r, c, h, w):
    """A floor 1.2 m below the sensor seen at a grazing angle up to a wall at 11 m."""
    d = rays(r, c, h, w)
    return nearest(plane_range(*d, (0.0, 1.0, 0.0), 1.2), plane_range(*d, (0, 0, 1.0), 10.5))


def sc_fence(r, c, h, w):
    """Posts at 4 m, 1 and 2 pixels wide alternately (gaps of 4), a 1-pixel rail at
    row 20, in front of a wall at 6 m."""
    cc = np.floor(c).astype(int) % 12
    post = (cc == 4) | (cc == 9) | (cc == 10)
    rail = np.floor(r).astype(int) == 20
    return np.where(post | rail, 4.0, 6.0 + 0.0 * r)


def sc_wire(r, c, h, w):
    """A 1-pixel wire on the diagonal (r = c) and one at 20 degrees, at 3 m, in front of
    a wall at 5 m slanted 1 cm a pixel."""
    diag = np.floor(r) == np.floor(c)
    a = np.deg2rad(20.0)
    w20 = np.abs((r - h / 2) * np.cos(a) - (c - w / 2) * np.sin(a)) < 0.5
    return np.where(diag | w20, 3.0, 5.0 + 0.01 * c)


def _edge(theta_deg):
    def f(r, c, h, w):
        a = np.deg2rad(theta_deg)
        near = (r - h / 2) * np.cos(a) - (c - w / 2) * np.sin(a) > 0
        return np.where(near, 3.0 + 0.005 * c, 6.0 + 0.01 * r)
    return f


sc_edge12 = _edge(12.0)
sc_edge45 = _edge(45.0)

TRI = np.array([(10.0, 4.0), (30.0, 60.0), (54.0, 56.0)])


def sc_triangle(r, c, h, w):
    """A triangle (acute corners, vertices scaled from a 64 x 64 frame) at 4 m tilted, on
    a wall at 7 m."""
    v = TRI * np.array([h / 64, w / 64])
    inside = np.ones(np.shape(r), bool)
    sgn = None
    for i in range(3):
        (r1, c1), (r2, c2) = v[i], v[(i + 1) % 3]
        s = (c2 - c1) * (r - r1) - (r2 - r1) * (c - c1)
        sgn = np.sign(s) if sgn is None else sgn
        inside &= s * np.sign((c2 - c1) * (v[(i + 2) % 3][0] - r1)
                              - (r2 - r1) * (v[(i + 2) % 3][1] - c1)) > 0
    return np.where(inside, 4.0 + 0.01 * r, 7.0 + 0.0 * c)


def sc_mostly_sky(r, c, h, w):
    """A disc of radius 11 px (about 9 % of 64 x 64) at 5 m; the rest sky."""
    disc = (r - 0.6 * h) ** 2 + (c - 0.4 * w) ** 2 < (11 * min(h, w) / 64) ** 2
    return np.where(disc, 5.0 + 0.01 * r, np.nan)


def sc_sky(r, c, h, w):
    return np.full(np.shape(r), np.nan)


SCENES = {
    "sphere": sc_sphere, "cylinder": sc_cylinder, "steep10cm": sc_steep,
    "steep_diag": sc_steep_diag, "grazing": sc_grazing, "fence": sc_fence,
    "wire": sc_wire, "edge12": sc_edge12, "edge45": sc_edge45, "triangle": sc_triangle,
    "mostly_sky": sc_mostly_sky, "sky": sc_sky,
}


def truth(scene, h, w, ss=1):
    """(h, w, ss*ss) ranges at sub-pixel centres (ss = 1: the pixel centre)."""
    o = (np.arange(ss) + 0.5) / ss
    rr = np.arange(h)[:, None, None, None] + o[None, None, :, None]
    cc = np.arange(w)[None, :, None, None] + o[None, None, None, :]
    rr, cc = np.broadcast_arrays(rr, cc)
    return scene(rr.astype(float), cc.astype(float), h, w).reshape(h, w, ss * ss)


def bg_profile(kind, n=N_BINS):
    x = (np.arange(n) + 0.5) / n
    if kind == "flat":
        p = np.ones(n)
    elif kind == "ramp3":
        p = 1 + 2 * x            # rises linearly by 3x over the bins
    elif kind == "exp3":
        p = np.exp(-3 * x)       # pile-up-like decay
    elif kind == "exp1":
        p = np.exp(-x)
    else:
        raise ValueError(kind)
    return p / p.sum()


def reflectance(kind, h, w):
    """The signal's factor a pixel (h, w), mean 1: "flat" (1 everywhere), "checker"
    (squares of 8 pixels at 0.25 and 1.75: a 7x contrast, each square's edges inside
    the scene's surfaces), "ramp" (0.2 at the left border rising linearly to 1.8 at the
    right: a 9x contrast across the frame)."""
    r, c = np.mgrid[0:h, 0:w]
    if kind == "flat":
        return np.ones((h, w))
    if kind == "checker":
        return np.where((r // 8 + c // 8) % 2 == 0, 0.25, 1.75)
    if kind == "ramp":
        return 0.2 + 1.6 * c / max(w - 1, 1)
    raise ValueError(f"no such reflectance: {kind!r} (flat, checker, ramp)")


def histograms(scene, h, w, signal, background, rng, ss=1, pulse_sigma_s=SIGMA_S,
               bg="flat", refl="flat"):
    """Counts (h, w, N_BINS) int64. Signal: Poisson(signal x the pixel's reflectance)
    photons a pixel, each at a uniformly drawn sub-pixel (lost if that sub-pixel is
    sky), time 2 R / c + N(0, pulse_sigma). Background: Poisson(background) photons a
    pixel, bins drawn from the profile. Returns counts and the truth (h, w, ss*ss)."""
    rng = np.random.default_rng(rng)
    tr = truth(scene, h, w, ss)
    npix = h * w
    n = rng.poisson(signal * reflectance(refl, h, w).ravel(), npix)
    who = np.repeat(np.arange(npix), n)
    sub = rng.integers(0, ss * ss, who.size)
    d = tr.reshape(npix, ss * ss)[who, sub]
    ok = np.isfinite(d)
    t = 2 * d[ok] / C + rng.normal(0, pulse_sigma_s, ok.sum())
    b = np.floor(t / BIN_S).astype(np.int64)
    inb = (b >= 0) & (b < N_BINS)
    idx = who[ok][inb] * N_BINS + b[inb]
    nb = rng.poisson(background, npix)
    whob = np.repeat(np.arange(npix), nb)
    bb = rng.choice(N_BINS, whob.size, p=bg_profile(bg))
    idx = np.concatenate([idx, whob * N_BINS + bb])
    out = np.bincount(idx, minlength=npix * N_BINS).reshape(h, w, N_BINS)
    return out, tr


def sc_flatwall(r, c, h, w):
    """A flat wall facing the sensor at 7 m, ray-cast (range = 7 / cos(angle off axis))."""
    d = rays(r, c, h, w)
    return plane_range(*d, (0.0, 0.0, 1.0), 7.0)


def sc_bigsphere(r, c, h, w):
    """A sphere of radius 3 m whose front is at 4 m, filling the frame's centre, on a
    wall at 9 m facing the sensor."""
    d = rays(r, c, h, w)
    return nearest(sphere_range(*d, (0.0, 0.0, 7.0), 3.0), plane_range(*d, (0, 0, 1.0), 9.0))


SCENES["flatwall"] = sc_flatwall
SCENES["bigsphere"] = sc_bigsphere


def _flatwall_fov(fov):
    def f(r, c, h, w):
        d = rays(r, c, h, w, fov_deg=fov)
        return plane_range(*d, (0.0, 0.0, 1.0), 7.0)
    return f


SCENES["flatwall_fov20"] = _flatwall_fov(20.0)
SCENES["flatwall_fov10"] = _flatwall_fov(10.0)
