"""Where the spatial estimator's sigma under-covers (issue 35): its 2-sigma coverage by
kind of pixel on Lindell's scene (benchmarks/spatial_scenes.py), and on a plain depth
edge, how the estimate's spread grows towards the edge against the sigma it reports.

Kinds (detected pixels that have a surface, the strongest return): ``jump`` a pixel whose
8 nearest hold another surface more than 0.3 m away (not sky), ``sky edge`` one beside
empty sky, ``near`` 2-3 pixels from such a jump, ``steep`` a surface changing > 5 cm a
pixel elsewhere, ``flat`` the rest away from the image's border, ``two`` the pane's
pixels (two surfaces). The edge: a 48 x 24 image, a fronto-parallel surface on its left
12 columns, empty sky (or a surface 3 m further) on the right; the estimate's bias and
spread (bins) per column against the median sigma it reports, and the coverage (a
detected estimate more than 20 bins off, on the other surface, counted apart).

    python benchmarks/spatial_edges.py [--seeds 1,2,3,4] [--cells "5,50 2,50"]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.spatial_scenes import BIN_S, SIGMA_S, C, Scene, histograms, scene  # noqa: E402
from stages.ranging.spatial import spatial  # noqa: E402


def kinds(sc: Scene) -> dict[str, np.ndarray]:
    d0 = sc.depth[..., 0]
    h, w = d0.shape
    pad = np.pad(d0, 3, mode="edge")

    def beside(k, test):
        out = np.zeros((h, w), bool)
        for i in range(-k, k + 1):
            for j in range(-k, k + 1):
                if (i, j) != (0, 0):
                    out |= test(pad[3 + i:3 + i + h, 3 + j:3 + j + w])
        return out & np.isfinite(d0)

    jump1 = beside(1, lambda nb: np.abs(nb - d0) > 0.3)
    sky1 = beside(1, np.isnan)
    jump3 = beside(3, lambda nb: ~(np.abs(nb - d0) <= 0.3))
    rr, cc = np.mgrid[0:h, 0:w]
    border = (rr < 3) | (rr >= h - 3) | (cc < 3) | (cc >= w - 3)
    two = np.isfinite(sc.depth[..., 1])
    steep = np.hypot(*np.gradient(d0)) > 0.05
    return {"jump": jump1 & ~sky1, "sky edge": sky1, "near": jump3 & ~jump1 & ~sky1,
            "steep": steep & ~jump3 & ~border, "flat": ~steep & ~jump3 & ~two & ~border,
            "two": two}


def by_kind(seeds, cells, threads) -> None:
    sc = scene()
    k = kinds(sc)
    print("| signal | background | seed | all | " + " | ".join(k) + " |")
    print("|---:|---:|---:|---:|" + "---:|" * len(k))
    for s, b in cells:
        for seed in seeds:
            e = spatial(histograms(sc, s, b, seed), BIN_S, SIGMA_S, threads=threads)
            dm = e.t_s[..., 0] * C / 2
            err = np.fmin(np.abs(dm - sc.depth[..., 0]),
                          np.nan_to_num(np.abs(dm - sc.depth[..., 1]), nan=np.inf))
            z = err / (e.sigma_s[..., 0] * C / 2)
            det = e.detected[..., 0] & sc.surface

            def cov(m, det=det, z=z):
                m = m & det
                return f"{np.mean(z[m] < 2):.3f} ({m.sum()})" if m.any() else "-"

            print(f"| {s} | {b} | {seed} | {cov(np.ones_like(det))} | "
                  + " | ".join(cov(m) for m in k.values()) + " |", flush=True)


def edge(seeds, threads) -> None:
    h, w = 48, 24
    cols = (6, 9, 10, 11)
    print("\n| right of the edge | column (edge: 11) | bias bins | spread bins | median "
          "sigma bins | within 2 sigma | on the other surface |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for other in ("sky", "3 m further"):
        d = 300.25 * BIN_S * C / 2
        depth = np.full((h, w, 2), np.nan)
        share = np.zeros((h, w, 2))
        share[..., 0] = 1
        depth[:, :12, 0] = d
        if other != "sky":
            depth[:, 12:, 0] = d + 3.0
        sc = Scene(depth, share)
        got = {c: ([], [], [], []) for c in cols}
        for seed in seeds:
            e = spatial(histograms(sc, 5, 50, 100 + seed), BIN_S, SIGMA_S, threads=threads)
            for c in cols:
                err = (e.t_s[5:-5, c, 0] - 2 * d / C) / BIN_S
                far = np.abs(err) > 20             # on the other surface: counted apart
                ok = e.detected[5:-5, c, 0] & ~far
                got[c][3].append(int((e.detected[5:-5, c, 0] & far).sum()))
                err = err[ok]
                sg = e.sigma_s[5:-5, c, 0][ok] / BIN_S
                got[c][0].extend(err)
                got[c][1].extend(sg)
                got[c][2].extend(np.abs(err) < 2 * sg)
        for c in cols:
            err, sg, ok = (np.asarray(x) for x in got[c][:3])
            print(f"| {other} | {c} | {err.mean():+.2f} | {err.std():.2f} | "
                  f"{np.median(sg):.2f} | {ok.mean():.2f} | {sum(got[c][3])} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="1,2,3,4")
    ap.add_argument("--cells", default="5,50 2,50")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    seeds = [int(x) for x in a.seeds.split(",")]
    cells = [tuple(int(v) for v in c.split(",")) for c in a.cells.split()]
    print("$ python benchmarks/spatial_edges.py " + " ".join(sys.argv[1:]))
    print(f"load average {os.getloadavg()[0]:.1f}, spatial with {a.threads} thread(s)\n")
    by_kind(seeds, cells, a.threads)
    edge(seeds, a.threads)


if __name__ == "__main__":
    main()
