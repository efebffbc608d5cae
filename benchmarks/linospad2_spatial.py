"""Real LinoSPAD2 background, known surfaces: the sample capture (tests/data/linospad2,
uniform light, no laser) folded on an 80 ns laser period with the board's code-density
table (``pipeline.io.linospad2_tof``: 256 pixels x 1 024 bins of 78.125 ps, ~514 real
background photons a pixel), plus signal photons drawn here: a plane at 3.0 m (pixels
0-99), a depth edge to a slanted plane 4.0 -> 4.8 m (100-179), empty sky (180-255), each
return Gaussian of sigma 42.5 ps (the system's ~100 ps FWHM) with a Poisson number of
photons of mean S a pixel. Ranged per pixel (``ml``) and with the neighbours (``--spatial
--geometry linospad2``), P_fa 1e-3 a pixel, ``--delay-ps 0 --irf-ps 42.5``. Prints the
command, the machine and a Markdown table.

    python benchmarks/linospad2_spatial.py [--out benchmarks/results/linospad2_spatial.md]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
from scipy.constants import c as C_LIGHT

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.datapath import emit, machine  # noqa: E402
from pipeline.io.geometry import load_geometry  # noqa: E402
from pipeline.io.linospad2 import read_published_calibration  # noqa: E402
from pipeline.io.linospad2_tof import tof_counts, tof_table  # noqa: E402
from pipeline.offline.generic import range_generic  # noqa: E402
from pipeline.offline.spatial import range_spatial  # noqa: E402

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "linospad2"
DAT = DATA / "test_data_2212b.dat"
CSV = DATA / "TDC_A5_#36_2212b.csv"
PERIOD_PS, BINS, SIGMA_PS, P_FA = 80_000.0, 1024, 42.5, 1e-3
SIGNALS = (2, 5, 10, 20)


def scene() -> np.ndarray:
    """The true distance of each of the 256 pixels (NaN: no surface)."""
    d = np.full(256, np.nan)
    d[:100] = 3.0
    d[100:180] = np.linspace(4.0, 4.8, 80)
    return d


def with_signal(background: np.ndarray, truth: np.ndarray, mean: float,
                rng: np.random.Generator) -> np.ndarray:
    """``background`` (256, BINS) plus each surface pixel's Poisson(mean) photons."""
    out = background.copy()
    width = PERIOD_PS / BINS
    for p in np.flatnonzero(np.isfinite(truth)):
        t = rng.normal(2 * truth[p] / C_LIGHT * 1e12, SIGMA_PS, rng.poisson(mean))
        np.add.at(out[p], np.floor(t / width).astype(np.int64) % BINS, 1)
    return out


def score(table, truth: np.ndarray) -> dict:
    """Return 0 of each pixel against the truth: the surface pixels' detections, their
    errors (m) and sigmas (m), the sky pixels' detections."""
    tdc = np.asarray(table.column("tdc").to_numpy())
    first = np.asarray(table.column("return_index").to_numpy()) == 0
    det = np.asarray(table.column("detected").to_numpy(zero_copy_only=False), bool)
    d = np.asarray(table.column("distance_m").to_numpy(zero_copy_only=False), np.float64)
    s = np.asarray(table.column("sigma_m").to_numpy(zero_copy_only=False), np.float64)
    p, det, d, s = tdc[first], det[first], d[first], s[first]
    surf = np.isfinite(truth[p])
    hit = det & surf
    return {"surface": int(surf.sum()), "detected": int(hit.sum()),
            "err": d[hit] - truth[p[hit]], "sigma": s[hit],
            "sky": int((~surf).sum()), "false": int((det & ~surf).sum())}


def summary(parts: list[dict]) -> dict:
    """The runs of one signal level and estimator pooled; outliers: > 5 cm off."""
    err = np.concatenate([r["err"] for r in parts])
    sig = np.concatenate([r["sigma"] for r in parts])
    good = np.abs(err) < 0.05
    e, sg = err[good], sig[good]
    return {"surface": sum(r["surface"] for r in parts),
            "detected": sum(r["detected"] for r in parts), "outliers": int((~good).sum()),
            "rmse_mm": float(np.sqrt(np.mean(e ** 2)) * 1e3) if e.size else np.nan,
            "cover": float(np.mean(np.abs(e) <= 2 * sg)) if e.size else np.nan,
            "median_sigma_mm": float(np.median(sg) * 1e3) if e.size else np.nan,
            "sky": sum(r["sky"] for r in parts), "false": sum(r["false"] for r in parts)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--runs", type=int, default=5, help="signal draws a level")
    a = ap.parse_args(argv)
    rng = np.random.default_rng(a.seed)
    background, _ = tof_counts(DAT, PERIOD_PS, BINS, read_published_calibration(CSV))
    truth = scene()
    geom = load_geometry("linospad2")
    ranged: dict[tuple[int, str], list] = {}
    seconds: dict[tuple[int, str], float] = {}
    with tempfile.TemporaryDirectory() as d:
        for mean in SIGNALS:
            for k in range(a.runs):
                h = Path(d) / f"s{mean}_{k}.parquet"
                pq.write_table(tof_table(with_signal(background, truth, mean, rng),
                                         PERIOD_PS, f"s{mean}_{k}"), h)
                for name, run in (
                        ("per pixel (ml)", lambda h=h: range_generic(
                            h, None, 0.0, None, SIGMA_PS * 1e-12, "ml", P_FA)[0]),
                        ("spatial", lambda h=h: range_spatial(
                            h, 0.0, SIGMA_PS * 1e-12, P_FA, geom)[0])):
                    t0 = time.perf_counter()
                    ranged.setdefault((mean, name), []).append(score(run(), truth))
                    seconds[(mean, name)] = (seconds.get((mean, name), 0.0)
                                             + time.perf_counter() - t0)
    cmd = "python benchmarks/linospad2_spatial.py" + (f" --seed {a.seed}" if a.seed else "") \
        + (f" --runs {a.runs}" if a.runs != 5 else "")
    lines = [f"`{cmd}` ({a.runs} signal draws a level on the one real background)", "",
             f"Machine: {machine()}", "",
             "| signal / pixel | estimator | surface pixels detected | outliers (> 5 cm) "
             "| RMSE (mm, the rest) | within 2 sigma | median sigma (mm) | false surfaces "
             "in sky pixels | s a frame |", "|---|---|---|---|---|---|---|---|---|"]
    for (mean, name), parts in ranged.items():
        r = summary(parts)
        lines.append(f"| {mean} | {name} | {r['detected']} of {r['surface']} | "
                     f"{r['outliers']} | {r['rmse_mm']:.2f} | {r['cover']:.1%} | "
                     f"{r['median_sigma_mm']:.2f} | {r['false']} of {r['sky']} | "
                     f"{seconds[(mean, name)] / a.runs:.2f} |")
    emit(lines, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
