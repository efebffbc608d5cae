"""A response with a diffusion tail under the spatial estimator: false second surfaces
and the real ones, with the rise test (step 3, ``spatial.RISE``) and without it.

A SPAD's response is not the Gaussian pulse the spatial estimator models: a share of
its photons come late, an exponential delay of its slow carriers (0.1-1 ns on the
chips and sensors of docs/ranging.md "Real responses"). Each frame here is a slanted
plane 5 m away on 64 x 64 pixels (1 024 bins of 80 ps, a 440-ps FWHM pulse), drawn
photon by photon (numpy; nothing of the estimator's): each photon's time is the pulse's
Gaussian and, for ``frac`` of them, an exponential delay of mean ``tau`` (the last rows:
a gamma of shape 8, a peaked delay). Some rows add a second plane behind the right half.
Per row, off, on, and on with the response measured (``spatial.measure_response`` on a
flat frame 1 m away of 100 photons a pixel and the same response, as `range --spatial
--zero` measures it): the share of two-surface pixels whose second surface is detected
(a detected return within 5 cm of it), and the share of pixels with a detected return
on neither surface (> 5 cm from both: a false surface), and the first return's median
error, over ``--seeds`` frames.

    python benchmarks/spatial_tail.py [--seeds 1-2]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from stages.ranging import spatial as sp  # noqa: E402

C = 299_792_458.0
BIN_S, N_BINS = 80e-12, 1024
SIGMA_S = 440e-12 / (2 * np.sqrt(2 * np.log(2)))

# signal, background photons a pixel; the tail's share and mean (s); the second plane
# (metres behind, photons a pixel) or None
ROWS = [
    (20, 2, 0.0, 0.0, None), (100, 10, 0.0, 0.0, None),
    (20, 2, 0.3, 5e-10, None), (100, 2, 0.3, 5e-10, None), (100, 10, 0.3, 5e-10, None),
    (30, 10, 0.3, 1e-9, None), (100, 10, 0.3, 1e-9, None), (100, 2, 0.3, 2e-9, None),
    (20, 2, 0.0, 0.0, (1.0, 10)), (20, 2, 0.0, 0.0, (0.3, 5)), (10, 10, 0.0, 0.0, (0.5, 3)),
    (5, 10, 0.0, 0.0, (0.3, 5)), (5, 10, 0.0, 0.0, (1.0, 2)), (2, 50, 0.0, 0.0, (1.0, 2)),
    (100, 10, 0.3, 1e-9, (0.5, 10)), (100, 10, 0.3, 1e-9, (1.5, 10)),
    (20, 2, 0.3, 5e-10, (0.3, 10)),
    (100, 10, 0.3, 1e-9, (0.5, 3)), (100, 10, 0.3, 1e-9, (0.5, 2)), (30, 10, 0.3, 1e-9, (0.5, 2)),
    # a peaked delay (a gamma of shape 8: a bump behind the pulse)
    (100, 10, 0.3, 1e-9, None, 8.0), (30, 10, 0.3, 2e-9, None, 8.0),
    (100, 10, 0.3, 2e-9, None, 8.0), (100, 10, 0.3, 3e-9, None, 8.0),
    (100, 10, 0.3, 2e-9, (1.0, 10), 8.0), (100, 10, 0.3, 2e-9, (1.5, 10), 8.0),
    (100, 10, 0.3, 2e-9, (0.5, 10), 8.0),
]


def frame(rng, signal, background, frac, tau, second, h=64, w=64, base_m=5.0, tilt=True,
          shape=1.0):
    """Counts (h, w, bins) and the two planes' depths (m; the second NaN where none):
    the first plane ``base_m`` away at the first pixel, 1 and 0.5 cm further a row and a
    column (``tilt``; else flat). The late photons' delay is a gamma of mean ``tau`` and
    ``shape`` (1: the exponential; 8: a peaked delay, a bump behind the pulse)."""
    rr, cc = np.mgrid[0:h, 0:w]
    d1 = base_m + (0.01 * rr + 0.005 * cc if tilt else 0.0 * rr)
    d2 = np.where(cc >= w // 2, d1 + (second[0] if second else np.nan), np.nan)
    counts = np.zeros(h * w * N_BINS, np.int64)
    for d, s in ((d1, signal), (d2, second[1] if second else 0)):
        k = np.where(np.isfinite(d), rng.poisson(s, (h, w)), 0)
        idx = np.repeat(np.arange(h * w), k.ravel())
        t = 2 * np.nan_to_num(d).ravel()[idx] / C + rng.normal(0, SIGMA_S, idx.size)
        late = rng.random(idx.size) < frac
        t[late] += rng.gamma(shape, tau / shape, late.sum()) if tau else 0.0
        np.add.at(counts, idx * N_BINS + np.clip((t / BIN_S).astype(int), 0, N_BINS - 1), 1)
    return counts.reshape(h, w, N_BINS) + rng.poisson(background / N_BINS, (h, w, N_BINS)), d1, d2


def score(est, d1, d2):
    d = est.t_s * C / 2
    two = np.isfinite(d2)
    hit = (est.detected & (np.abs(d - d2[..., None]) < 0.05)).any(-1)
    false = (est.detected & (np.abs(d - d1[..., None]) > 0.05)
             & ~(np.abs(d - d2[..., None]) < 0.05)).any(-1)
    first = np.nanmedian(d[..., 0] - d1) * 1e3
    return (hit[two].mean() if two.any() else np.nan), false.mean(), first


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1-2")
    a = ap.parse_args()
    lo, _, hi = a.seeds.partition("-")
    seeds = range(int(lo), int(hi or lo) + 1)
    shipped = sp.RISE
    print(f"command: python benchmarks/spatial_tail.py --seeds {a.seeds}")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, python "
          f"{platform.python_version()}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    print()
    print("| signal | background | tail share | tail mean ns | delay's shape "
          "| second (m behind, photons) | second found off -> on -> response "
          "| false surfaces off -> on -> response | first's median error mm |")
    print("|---:|---:|---:|---:|---:|---|---|---|---:|")
    for s, b, frac, tau, second, *shape in ROWS:
        shape = shape[0] if shape else 1.0
        got = {"off": [], "on": [], "response": []}
        for seed in seeds:
            zero = frame(np.random.default_rng(1000 + seed), 100, 10, frac, tau, None,
                         base_m=1.0, tilt=False, shape=shape)[0]
            resp = sp.measure_response(zero, sp.spatial(zero, BIN_S, SIGMA_S, 1e-3,
                                                         max_returns=1, threads=2), BIN_S)
            counts, d1, d2 = frame(np.random.default_rng(seed), s, b, frac, tau, second,
                                   shape=shape)
            for name, rise, kw in (("off", 0, {}), ("on", shipped, {}),
                                   ("response", shipped, {"response": resp})):
                sp.RISE = rise
                got[name].append(score(sp.spatial(counts, BIN_S, SIGMA_S, 1e-3, threads=2,
                                                  **kw), d1, d2))
        sp.RISE = shipped
        off, on, rs = (np.mean(got[k], 0) for k in ("off", "on", "response"))
        sec = "-" if second is None else f"{second[0]:g}, {second[1]}"
        found = "-" if second is None else f"{off[0]:.1%} -> {on[0]:.1%} -> {rs[0]:.1%}"
        print(f"| {s} | {b} | {frac:g} | {tau * 1e9:g} | {shape:g} | {sec} | {found} | "
              f"{off[1]:.2%} -> {on[1]:.2%} -> {rs[1]:.2%} | {on[2]:.1f} |", flush=True)


if __name__ == "__main__":
    main()
