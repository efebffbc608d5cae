"""Calibration accuracy against the density test's length: LSB, INL and delay errors
against the simulator's truth, and the time each length took.

For each number of density-test cycles: a density test at ``--density-lux`` (uniform
light), then the delay (eq. 5.3) from a zero-distance capture with ambient light at
``--delay-lux`` (brighter, so its own reset peak falls on codes the density test measured
and scales the time axis at its light; the peak by the range stage's ML), both simulated
in memory (``SimulatedCapture``: the words a capture would hold, not written). The delay's
error is the density test's INL statistics at the peak's code: it falls as 1/sqrt(cycles),
and the table extrapolates the cycles that 5 ps needs.

With ``--fill-lux``, a second density test of the same length at that (dimmer) light
measures the codes under the first one's reset peak, and the INL takes their widths from
it (as ``lsb_campaign`` does with its tests; the INL columns are then the filled table's).

    python benchmarks/calibration.py [--cycles 1e6 4e6 1.6e7 6.4e7] [--tdcs 8]
        [--density-lux 2411.097] [--fill-lux 1205.548]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.datapath import emit, machine  # noqa: E402
from pipeline.offline.calibrate import (  # noqa: E402
    add_delay,
    density_histograms,
    refilled,
    write_caldir,
)
from pipeline.offline.simulate import SimulatedCapture  # noqa: E402
from stages import calibration as cal  # noqa: E402
from stages.models.scene import scene_from_dict  # noqa: E402

C_LIGHT = 299_792_458.0


def scenes(n_tdc: int, density_lux: float, delay_lux: float, delay_ns: float = 100.0):
    sensor = {"n_pixels": n_tdc, "hot_pixels": []}
    dens = scene_from_dict({"name": "density", "sensor": sensor, "dark_counts": True,
                            "ambient": [{"kind": "lux", "lux": density_lux}]})
    delay = scene_from_dict({
        "name": "delay", "sensor": sensor, "dark_counts": True,
        "gate": {"t_laser_win_ns": 140.0, "delay_ns": delay_ns},
        "ambient": [{"kind": "lux", "lux": delay_lux}],
        "targets": [{"pixels": [0, n_tdc - 1], "distance_m": 0.001, "reflectivity": 0.0005,
                     "surface": "mirror"}]})
    return dens, delay


def one(cycles: int, args, tmp: Path) -> dict:
    dens, delay = scenes(args.tdcs, args.density_lux, args.delay_lux)
    t0 = time.perf_counter()
    cap = SimulatedCapture(dens, cycles, chip_seed=args.chip_seed, seed=1)
    state, second = density_histograms(cap)
    arts = None if args.no_artifacts else state.artifacts
    res = cal.density_test(state.hits, state.cycles, cap.meta.window_ns * 1e-9, artifacts=arts)
    if args.fill_lux:
        dim, _ = scenes(args.tdcs, args.fill_lux, args.delay_lux)
        st2, _ = density_histograms(SimulatedCapture(dim, cycles, chip_seed=args.chip_seed,
                                                     seed=3))
        if args.no_artifacts:
            state, st2 = (replace(s, artifacts=None) for s in (state, st2))
        r2 = cal.density_test(st2.hits, st2.cycles, cap.meta.window_ns * 1e-9,
                              artifacts=st2.artifacts)
        res = refilled(state, res, [(st2, r2)], cap.meta.window_ns * 1e-9)
    t_density = time.perf_counter() - t0
    truth = cap.truth["chip"]
    lsb_err = res.lsb_s * 1e12 - np.array(truth["lsb_window_ps"])
    inl_t = np.array(truth["inl_window_lsb"])
    x_t = np.array(truth["x_t"])
    k = np.arange(inl_t.shape[1])
    inl_rms, untilted = np.empty(args.tdcs), np.empty(args.tdcs)
    for t in range(args.tdcs):
        m = (k < x_t[t] - 1) & np.isfinite(res.inl_lsb[t])
        e = (res.inl_lsb[t] - inl_t[t])[m]
        inl_rms[t] = np.sqrt(np.mean(e ** 2))
        # less a straight line through code 0: the tilt the filled codes under the reset
        # peak give the table (their summed width error rescales every boundary)
        a = np.sum(e * k[m]) / np.sum(k[m] ** 2.0)
        untilted[t] = np.sqrt(np.mean((e - a * k[m]) ** 2))
    caldir = write_caldir(tmp / f"cal-{cycles}", res, second, [])
    t1 = time.perf_counter()
    dcap = SimulatedCapture(delay, args.delay_cycles, chip_seed=args.chip_seed, seed=2)
    d = add_delay(dcap, caldir).delay_s
    t_delay = time.perf_counter() - t1
    err = (d - (100e-9 + 2 * 0.001 / C_LIGHT)) * 1e12
    return {"cycles": cycles, "density_s": t_density, "delay_s": t_delay,
            "light": cap.sim.light, "delay_light": dcap.sim.light,
            "lsb_max_ps": float(np.abs(lsb_err).max()),
            "inl_median": float(np.median(inl_rms)), "inl_max": float(inl_rms.max()),
            "untilted_median": float(np.median(untilted)),
            "untilted_max": float(untilted.max()),
            "inl_predicted": float(np.nanmedian(res.inl_error_lsb)),
            "delay_rms_ps": float(np.sqrt(np.nanmean(err ** 2))),
            "delay_max_ps": float(np.nanmax(np.abs(err)))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=float, nargs="+", default=[1e6, 4e6, 1.6e7, 6.4e7])
    ap.add_argument("--tdcs", type=int, default=8)
    ap.add_argument("--density-lux", type=float, default=2411.097)
    ap.add_argument("--delay-lux", type=float, default=13_394.983)
    ap.add_argument("--no-artifacts", action="store_true",
                    help="leave the artifact STARTs out of the at-risk counts (as before)")
    ap.add_argument("--fill-lux", type=float, default=None,
                    help="a second density test at this light fills the first one's codes "
                         "under its reset peak")
    ap.add_argument("--delay-cycles", type=int, default=4_000_000)
    ap.add_argument("--chip-seed", type=int, default=4)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/calibration.md"))
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for c in args.cycles:
            rows.append(one(int(c), args, Path(d)))
            r = rows[-1]
            print(f"{r['cycles']:.1e} cycles: delay RMS {r['delay_rms_ps']:.1f} ps "
                  f"({r['density_s'] + r['delay_s']:.0f} s)", file=sys.stderr)
    lines = [f"command: `python {' '.join(sys.argv)}`", f"machine: {machine()}", "",
             f"{args.tdcs} TDCs; density test at {args.density_lux:g} lux "
             f"({rows[0]['light']:.3f} STARTs per pixel per cycle); delay capture "
             f"{args.delay_cycles:,} cycles at {args.delay_lux:g} lux "
             f"({rows[0]['delay_light']:.3f}), scaled by its own reset peak."
             + (f" Codes under the density test's reset peak filled from a second test of "
                f"the same length at {args.fill_lux:g} lux." if args.fill_lux else ""), "",
             "| density cycles | density test s | delay s | LSB error max ps | "
             "INL RMS vs truth median / max LSB | the same less a tilt | INL predicted LSB | "
             "delay RMS ps | delay max ps |", "|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['cycles']:.1e} | {r['density_s']:.1f} | {r['delay_s']:.1f} | "
                     f"{r['lsb_max_ps']:.4f} | {r['inl_median']:.3f} / {r['inl_max']:.3f} | "
                     f"{r['untilted_median']:.3f} / {r['untilted_max']:.3f} | "
                     f"{r['inl_predicted']:.3f} | {r['delay_rms_ps']:.1f} | "
                     f"{r['delay_max_ps']:.1f} |")
    last = rows[-1]
    need_rms = last["cycles"] * (last["delay_rms_ps"] / 5.0) ** 2
    need_max = last["cycles"] * (last["delay_max_ps"] / 5.0) ** 2
    lines += ["", f"Extrapolated as 1/sqrt(cycles) from the longest test: a 5 ps RMS delay "
                  f"needs ~{need_rms:.1e} density cycles, every TDC within 5 ps ~"
                  f"{need_max:.1e} (at 102 us per cycle on the thesis's chip: "
                  f"{need_rms * 102e-6 / 3600:.1f} h and {need_max * 102e-6 / 3600:.1f} h)."]
    emit(lines, args.out)


if __name__ == "__main__":
    main()
