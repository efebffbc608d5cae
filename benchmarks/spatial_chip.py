"""Spatial ranging of a chip's captures (`range_state_spatial`: each TDC's calibrated
codes, less its delay, mapped onto one axis; docs/ranging.md "On the chip") against the
per-pixel `ml`, on simulated captures of the 16-TDC chip of scenes/small16.toml laid out
4 x 4: mirrors at 1.5 m (top half) and 2.5 m (bottom half) under 800 lux, and the same
chip with no target (false surfaces). Per reflectivity: the share of pixels detected,
the detected pixels' RMSE and 2-sigma coverage against the truth (with the sigma
written, which holds the calibration's own in quadrature, and with the estimator's
alone), and false surfaces in the empty captures (P_fa 1e-3 a pixel). (A detected pixel
more than 0.5 m off, on the other surface, is counted apart and left out of the RMSE
and the coverage.)

The calibration is built as the tests' (four density tests and a delay, tests/conftest.py
``caldir``), in a temporary directory, unless ``--cal``; ``--cal-seed`` N > 0 builds it
from other simulated captures (a chip calibrated again: other fixed errors a TDC).

    python benchmarks/spatial_chip.py [--seeds 20] [--cycles 6000] [--cal DIR]
        [--cal-seed 0]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.constants import c as C_LIGHT

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.io.caldir import load_calibration  # noqa: E402
from pipeline.io.capture import Capture  # noqa: E402
from pipeline.io.geometry import load_geometry  # noqa: E402
from pipeline.offline.ranging import range_state  # noqa: E402
from pipeline.offline.simulate import simulate_capture  # noqa: E402
from pipeline.offline.spatial import range_state_spatial  # noqa: E402
from stages.histogram import HistogramAccumulator  # noqa: E402
from stages.models.scene import scene_from_dict  # noqa: E402

N = 16


def calibration(d: Path, seed: int = 0) -> Path:
    from pipeline.offline.calibrate import add_delay, lsb_campaign

    caps = []
    for i, lux in enumerate((133.950, 535.799, 1607.398, 4018.495)):
        dens = scene_from_dict({"name": f"d{i}", "sensor": {"n_pixels": N},
                                "ambient": [{"kind": "lux", "lux": lux}]})
        simulate_capture(dens, 300_000, d / f"d{i}", seed=3 + i + 10 * seed)
        caps.append(d / f"d{i}")
    delay = scene_from_dict({"name": "z", "sensor": {"n_pixels": N},
                             "targets": [{"pixels": [0, N - 1], "distance_m": 0.001,
                                          "reflectivity": 0.0005, "surface": "mirror"}]})
    simulate_capture(delay, 150_000, d / "delay", seed=9 + 10 * seed)
    lsb_campaign(caps, d / "cal", inl_rms_lsb=1.0)
    add_delay(d / "delay", d / "cal")
    return d / "cal"


def scene(refl: float | None):
    targets = [] if refl is None else [
        {"pixels": [0, 7], "distance_m": 1.5, "reflectivity": refl, "surface": "mirror"},
        {"pixels": [8, 15], "distance_m": 2.5, "reflectivity": refl, "surface": "mirror"}]
    return scene_from_dict({"name": "edge16", "sensor": {"n_pixels": N},
                            "gate": {"t_laser_win_ns": 140.0, "delay_ns": 100.0},
                            "targets": targets, "ambient": [{"kind": "lux", "lux": 800.0}]})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--cycles", type=int, default=6000)
    ap.add_argument("--cal", type=Path, default=None)
    ap.add_argument("--cal-seed", type=int, default=0,
                    help="build the calibration from other captures (0: the tests')")
    a = ap.parse_args()
    print("$ python benchmarks/spatial_chip.py " + " ".join(sys.argv[1:]))
    print(f"load average {os.getloadavg()[0]:.1f}\n")
    truth = np.where(np.arange(N) < 8, 1.5, 2.5)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        cal = load_calibration(a.cal or calibration(tmp, a.cal_seed))
        g = tmp / "grid16.toml"
        g.write_text('name = "grid16"\n[grid]\nrows = 4\ncols = 4\nfov_h_deg = 10.0\n'
                     'fov_v_deg = 10.0\n')
        geom = load_geometry(g)
        print("| reflectivity | estimator | detected | on the other surface | RMSE detected mm "
              "| within 2 sigma | within 2 estimator's sigma | false surfaces | ms a capture |")
        print("|---:|---|---:|---:|---:|---:|---:|---:|---:|")
        for refl in (0.0002, 0.0005, 0.002, None):
            got = {"ml": [[], [], [], 0.0, [], 0], "spatial": [[], [], [], 0.0, [], 0]}
            for seed in range(a.seeds):
                out = tmp / f"c{refl}-{seed}"
                simulate_capture(scene(refl), a.cycles, out, seed=100 + seed)
                cap = Capture(out)
                acc = HistogramAccumulator(N, cal.bounds)
                for first, words in cap.iter_chunks():
                    acc.update(words, first)
                st = acc.snapshot()
                win, gate = cap.meta.window_ns * 1e-9, cap.meta.t_laser_win_ns * 1e-9
                for name in got:
                    t0 = time.process_time()
                    if name == "ml":
                        est, d, s, _ = range_state(st, cal, win, gate, "ml")
                    else:
                        est, d, s, _ = range_state_spatial(st, cal, win, gate, geom)
                    got[name][3] += time.process_time() - t0
                    first = (est.return_index == 0) if est.return_index is not None \
                        else np.ones(d.size, bool)
                    px = est.pixel[first] if est.pixel is not None else np.arange(N)
                    det = np.asarray(est.detected, bool)[first]
                    got[name][0].extend(det)
                    err = d[first] - truth[px]
                    own = np.asarray(est.sigma_s, np.float64)[first] * C_LIGHT / 2
                    near = det & (np.abs(err) < 0.5)
                    got[name][5] += int((det & ~near).sum())
                    got[name][1].extend(err[near])
                    got[name][2].extend((np.abs(err) < 2 * s[first])[near])
                    got[name][4].extend((np.abs(err) < 2 * own)[near])
            for name, (det, err, cov, cpu, cov_own, off) in got.items():
                det, err = np.asarray(det), np.asarray(err)
                label = "none (empty)" if refl is None else f"{refl:g}"
                if refl is None:
                    print(f"| {label} | {name} | | | | | | {det.sum()} of {det.size} | "
                          f"{cpu / a.seeds * 1e3:.0f} |")
                else:
                    print(f"| {label} | {name} | {det.mean():.3f} | {off} | "
                          f"{np.sqrt(np.mean(err ** 2)) * 1e3:.1f} | {np.mean(cov):.3f} | "
                          f"{np.mean(cov_own):.3f} | | {cpu / a.seeds * 1e3:.0f} |", flush=True)


if __name__ == "__main__":
    main()
