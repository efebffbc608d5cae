"""Range accuracy of the whole chain, and its error budget (issue 15).

A calibration campaign and a set of range captures, simulated with the project's simulator
(``Simulator.from_optics``: the chip of ``make_chip`` seen through given optics, words
through the project's datapath into histograms), calibrated and ranged with the project's
own code (``lsb_from_states`` = ``calibrate lsb``, ``delay_from_state`` = ``calibrate
delay``, ``range_state`` = ``tcspc range``), then scored against the simulator's truth.

Campaign: density tests at ``--density-n`` detections per pixel per cycle (uniform light;
the calibration flow's levels), ``--density-cycles`` each; a zero-distance capture at gate
140 ns with ambient light. Range sets (each ``--targets`` pixels, in captures of
``--tdcs`` pixels, each pixel its own distance, drawn uniformly where the return falls
4-76 ns into the window): gates 140, 300 and 500 ns at M = 0.03-0.15 detections a cycle
(log-uniform) and a brighter set at gate 140 ns with M = 0.5-2 (pile-up), ambient light
on all. System delay ``--delay-ns`` (70 ns: 0.5 m is in the 140 ns gate, 63 m in the
500 ns one).

The error budget reruns the calibration and ranging (never the simulation: the
histograms are cached under ``--cache``) with the simulator's truth in place of one
estimate at a time: the delay, the LSB at the capture's light (eq. 5.1), the INL (the
density test's, at its light), both (the exact time axis), and the instrument response
sigma; the last rows stack them. Truth is used here only, never by the estimators.

    python benchmarks/range_accuracy.py [--tdcs 32] [--density-cycles 4e6]
        [--range-cycles 20000] [--estimator ml] [--inl-from all|best] [--cache data/cache]
        [--out benchmarks/results/range_accuracy.md]
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.datapath import emit, machine  # noqa: E402
from pipeline.offline.calibrate import delay_from_state, lsb_from_states  # noqa: E402
from pipeline.offline.ranging import range_state  # noqa: E402
from stages import calibration as cal  # noqa: E402
from stages.calibration_set import Calibration  # noqa: E402
from stages.histogram import HistogramAccumulator, HistogramState  # noqa: E402
from stages.models.tcspc import combined_sigma, sigma_from_fwhm  # noqa: E402
from stages.simulator.chip import make_chip  # noqa: E402
from stages.simulator.engines import Optics  # noqa: E402
from stages.simulator.source import Simulator  # noqa: E402

C_LIGHT = 299_792_458.0
WINDOW_S = 80e-9
RESET_S = 20e-9           # the scene sensor's reset period before the window
#: laser pulse (44.8 ps FWHM), laser jitter (1.6 ps) and SPAD jitter (178.2 ps): as
#: ``optics_from_scene`` combines a default scene's
SIGMA_OPT_S = float(combined_sigma(sigma_from_fwhm(44.8e-12), 1.6e-12, 178.2e-12))
TOF_RANGE_S = (4e-9, 76e-9)  # where in the window a return is put (clear of both edges)
SECOND_STAGE_CYCLES = 1_000_000


# ------------------------------------------------------------------------ simulation

def bg_for_light(n: float) -> float:
    """Uniform background rate giving ``n`` STARTs per pixel per cycle (window + reset)."""
    return -np.log1p(-n) / (WINDOW_S + RESET_S)


def optics(m, tof_s, bg_hz, n_tdc) -> Optics:
    b = np.broadcast_to
    return Optics(np.array(b(m, n_tdc), np.float64), np.array(b(tof_s, n_tdc), np.float64),
                  SIGMA_OPT_S, np.array(b(bg_hz, n_tdc), np.float64),
                  WINDOW_S, RESET_S)


def simulate(chip, opt: Optics, cycles: int, seed: int, bounds=None, density=False):
    """The histograms the datapath makes of a simulated capture, and its light. A density
    test's second stage (Nmin/Nmax) from its first cycles, as `calibrate density` does
    from all of them (they are exact from far fewer)."""
    second = None
    if density:
        sim = Simulator.from_optics(opt, chip, seed)
        ss = cal.SecondStageAccumulator(chip.n_tdc)
        for first, words in sim.batches(min(cycles, SECOND_STAGE_CYCLES)):
            ss.update(words, first * chip.n_tdc)
        second = cal.second_stage_params(ss.counts)
        bounds = second.bounds
    sim = Simulator.from_optics(opt, chip, seed)
    acc = HistogramAccumulator(chip.n_tdc, bounds, count_artifacts=density)
    for first, words in sim.batches(cycles):
        acc.update(words, first * chip.n_tdc)
    return acc.snapshot(), second, sim.light


def _state_arrays(prefix, st: HistogramState) -> dict:
    out = {f"{prefix}hits": st.hits, f"{prefix}cc": st.class_counts,
           f"{prefix}words": np.array(st.words)}
    if st.artifacts is not None:
        out[f"{prefix}art"] = st.artifacts
    return out


def _state_from(z, prefix) -> HistogramState:
    art = z.get(f"{prefix}art")
    return HistogramState(z[f"{prefix}hits"], z[f"{prefix}cc"], int(z[f"{prefix}words"]),
                          artifacts=art)


def range_plan(args, rng):
    """The range sets: per capture its gate, per pixel M, distance and the ambient rate."""
    sets = [("gate 140 ns", 140e-9, (0.03, 0.15)), ("gate 300 ns", 300e-9, (0.03, 0.15)),
            ("gate 500 ns", 500e-9, (0.03, 0.15)), ("brighter, gate 140 ns", 140e-9,
                                                    (0.5, 2.0))]
    plan = []
    per = max(1, args.targets // args.tdcs)
    delay = args.delay_ns * 1e-9
    for name, gate, (m_lo, m_hi) in sets:
        for _ in range(per):
            tof = rng.uniform(*TOF_RANGE_S, args.tdcs)
            d = (tof + gate - WINDOW_S - delay) * C_LIGHT / 2
            d = np.clip(d, 0.5, 63.0)
            tof = delay + 2 * d / C_LIGHT - (gate - WINDOW_S)
            m = np.exp(rng.uniform(np.log(m_lo), np.log(m_hi), args.tdcs))
            plan.append({"set": name, "gate_s": gate, "distance_m": d, "tof_s": tof, "m": m,
                         "bg_hz": args.ambient_hz})
    return plan


def campaign(args):
    """Simulate everything once (cached): density tests, the delay capture, range sets."""
    key = hashlib.sha256(json.dumps({k: v for k, v in vars(args).items()
                                     if k in ("tdcs", "density_cycles", "density_n",
                                              "range_cycles", "targets", "chip_seed",
                                              "delay_ns", "ambient_hz", "delay_cycles",
                                              "delay_n", "seed")},
                                    sort_keys=True).encode()).hexdigest()[:12]
    path = args.cache / f"range_accuracy-{key}.npz"
    chip = make_chip(args.tdcs, args.chip_seed)
    plan = range_plan(args, np.random.default_rng(args.seed))
    if path.exists():
        z = dict(np.load(path, allow_pickle=False))
        tests = []
        for i in range(len(args.density_n)):
            sec = cal.SecondStage(*(z[f"d{i}_{f}"] for f in ("n_min", "n_max", "n_th", "pdm")))
            tests.append((_state_from(z, f"d{i}_"), sec))
        delay = _state_from(z, "z_")
        ranges = [_state_from(z, f"r{i}_") for i in range(len(plan))]
        return chip, plan, tests, [float(x) for x in z["d_light"]], delay, \
            float(z["z_light"]), ranges, [float(x) for x in z["r_light"]], 0.0
    t0 = time.perf_counter()
    arrays, tests, d_light = {}, [], []
    for i, n in enumerate(args.density_n):
        st, sec, light = simulate(chip, optics(0.0, 0.0, bg_for_light(n), args.tdcs),
                                  int(args.density_cycles), args.seed + 10 + i, density=True)
        tests.append((st, sec))
        d_light.append(light)
        arrays.update(_state_arrays(f"d{i}_", st))
        for f in ("n_min", "n_max", "n_th", "pdm"):
            arrays[f"d{i}_{f}"] = getattr(sec, f)
        print(f"density test {i}: n = {light:.3f}, {time.perf_counter() - t0:.0f} s",
              file=sys.stderr)
    bounds = tests[0][1].bounds
    delay_opt = optics(args.delay_m, args.delay_ns * 1e-9 - (140e-9 - WINDOW_S),
                       bg_for_light(args.delay_n), args.tdcs)
    delay, _, z_light = simulate(chip, delay_opt, args.delay_cycles, args.seed + 1, bounds)
    arrays.update(_state_arrays("z_", delay))
    ranges, r_light = [], []
    for i, p in enumerate(plan):
        st, _, light = simulate(chip, optics(p["m"], p["tof_s"], p["bg_hz"], args.tdcs),
                                args.range_cycles, args.seed + 100 + i, bounds)
        ranges.append(st)
        r_light.append(light)
        arrays.update(_state_arrays(f"r{i}_", st))
    arrays["d_light"], arrays["z_light"], arrays["r_light"] = (np.array(d_light), z_light,
                                                               np.array(r_light))
    args.cache.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)
    return chip, plan, tests, d_light, delay, z_light, ranges, r_light, \
        time.perf_counter() - t0


# ------------------------------------------------------------------- truth injected

@dataclasses.dataclass(frozen=True)
class _TrueLsb(Calibration):
    """A calibration whose LSB at a light (eq. 5.1) is the chip's true window LSB at the
    capture's true light (looked up from the measured one the time axis passes in)."""

    chip: object = None
    lights: dict | None = None

    def lsb_s(self, light: float):
        true_n = self.lights.get(round(float(light), 12), float(light))
        return self.chip.window_truth(true_n, WINDOW_S)[0], ""

    def rows(self, start: int, stop: int):
        if (start, stop) == (0, self.n_tdc):
            return self
        raise NotImplementedError("the benchmark ranges whole captures")


def true_inl_density(res: cal.DensityResult, chip, n_density: float) -> cal.DensityResult:
    """The density test with the chip's true INL at that test's light."""
    _, x_t, inl = chip.window_truth(n_density, WINDOW_S)
    return dataclasses.replace(res, inl_lsb=inl, x_t=x_t)


def measured_light(st: HistogramState) -> float:
    """The light as ``time_axis`` computes it from the histograms."""
    return round(float(st.hits.sum() / (st.hits.shape[0] * max(np.max(st.cycles), 1))), 12)


def run(config: set, base: Calibration, chip, plan, ranges, r_light, n_density, args,
        delay_state, z_light, estimator: str):
    """Range every capture with the causes in ``config`` replaced by truth; per-pixel
    errors (m), detections and the set of each pixel."""
    calib = base
    lights = {measured_light(st): li for st, li in zip(ranges, r_light, strict=True)}
    lights[measured_light(delay_state)] = z_light
    if "inl" in config:
        calib = dataclasses.replace(calib, density=true_inl_density(calib.density, chip,
                                                                    n_density))
    if "lsb" in config:
        fields = {f.name: getattr(calib, f.name) for f in dataclasses.fields(Calibration)
                  if f.init}  # (not the built-on-use cache)
        calib = _TrueLsb(**{**fields, "lsb_fit": None}, chip=chip, lights=lights)
    if "delay" in config:
        calib = dataclasses.replace(calib, delay_s=np.full(chip.n_tdc, args.delay_ns * 1e-9),
                                    delay_reasons=())
    else:  # the delay measured on this (possibly truth-injected) calibration
        calib = delay_from_state(calib, delay_state, WINDOW_S, 140e-9)
    errs, det, sets, sig = [], [], [], []
    for st, p, light in zip(ranges, plan, r_light, strict=True):
        sigma = None
        if "sigma" in config:
            sigma = float(np.median(np.hypot(SIGMA_OPT_S, chip.jitter_s(light))))
        est, d, s, _ = range_state(st, calib, WINDOW_S, p["gate_s"], estimator, sigma,
                                   in_situ=args.in_situ and "lsb" not in config)
        errs.append(d - p["distance_m"])
        det.append(np.asarray(est.detected, bool))
        sig.append(s)
        sets += [p["set"]] * d.size
    return np.concatenate(errs), np.concatenate(det), np.array(sets), np.concatenate(sig)


def summary(err, det, sets, sig) -> dict:
    ok = det & np.isfinite(err)
    e = err[ok] * 100
    out = {"rms": float(np.sqrt(np.mean(e ** 2))), "max": float(np.max(np.abs(e))),
           "bias": float(np.mean(e)), "detected": int(ok.sum()), "n": int(err.size),
           "stat": float(np.sqrt(np.mean((sig[ok] * 100) ** 2)))}
    for s in dict.fromkeys(sets):
        m = ok & (sets == s)
        out[s] = float(np.sqrt(np.mean((err[m] * 100) ** 2))) if m.any() else float("nan")
    return out


CONFIGS = [
    ("default chain (measured delay)", set()),
    ("true delay (the issue's setting)", {"delay"}),
    ("true delay + true LSB at the light", {"delay", "lsb"}),
    ("true delay + true INL", {"delay", "inl"}),
    ("true delay + true sigma (IRF)", {"delay", "sigma"}),
    ("true delay + exact time axis (INL and LSB)", {"delay", "lsb", "inl"}),
    ("true delay + exact axis + true sigma (estimator alone)", {"delay", "lsb", "inl",
                                                                "sigma"}),
    ("measured delay on the exact axis", {"lsb", "inl"}),
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tdcs", type=int, default=32)
    ap.add_argument("--targets", type=int, default=128, help="pixels per range set")
    ap.add_argument("--density-cycles", type=float, default=4e6)
    ap.add_argument("--density-n", type=float, nargs="+",
                    default=[0.02, 0.06, 0.15, 0.3, 0.5, 0.75])
    ap.add_argument("--range-cycles", type=int, default=20_000)
    ap.add_argument("--delay-cycles", type=int, default=2_000_000)
    ap.add_argument("--delay-n", type=float, default=0.5,
                    help="the delay capture's ambient light (STARTs per pixel per cycle)")
    ap.add_argument("--delay-m", type=float, default=0.05, help="its return, per cycle")
    ap.add_argument("--delay-ns", type=float, default=70.0)
    ap.add_argument("--ambient-hz", type=float, default=2e6,
                    help="the range captures' background rate")
    ap.add_argument("--estimator", default="ml")
    ap.add_argument("--in-situ", action="store_true",
                    help="range on the axis scaled by each capture's own reset peak")
    ap.add_argument("--inl-from", choices=["best", "all"], default="all",
                    help="the INL from the best density test (its reset-peak codes filled "
                         "from the others) or from all of them (inverse-variance)")
    ap.add_argument("--chip-seed", type=int, default=4)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--only", type=int, nargs="*", default=None,
                    help="run these rows of the table only")
    ap.add_argument("--cache", type=Path, default=Path("data/cache"))
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    chip, plan, tests, d_light, delay_state, z_light, ranges, r_light, t_sim = campaign(args)
    t0 = time.perf_counter()
    var: dict = {}  # the table's width variance, as `calibrate lsb` stores it
    best, second, fit, n, _, i_best = lsb_from_states(tests, WINDOW_S, inl_rms_lsb=1.0,
                                                      combine=args.inl_from == "all",
                                                      variance=var)
    base = Calibration(best, second, fit, np.full(chip.n_tdc, np.nan), (), None, {},
                       width_var_lsb2=var.get("width_var"))
    rows = []
    for i, (name, config) in enumerate(CONFIGS):
        if args.only is not None and i not in args.only:
            continue
        err, det, sets, sig = run(config, base, chip, plan, ranges, r_light, d_light[i_best],
                                args, delay_state, z_light, args.estimator)
        rows.append((name, config, summary(err, det, sets, sig)))
        print(f"{name}: {rows[-1][2]['rms']:.3f} cm RMS", file=sys.stderr)
    t_cal = time.perf_counter() - t0
    diag = diagnostics(base, chip, d_light[i_best], ranges, r_light, delay_state, z_light,
                       args)
    set_names = list(dict.fromkeys(p["set"] for p in plan))
    lines = [f"command: `python {' '.join(sys.argv)}`", f"machine: {machine()}", "",
             f"{len(plan) * args.tdcs} targets, 0.5-63 m ({len(plan)} captures of "
             f"{args.tdcs} pixels x {args.range_cycles:,} cycles; range-capture light "
             f"{min(r_light):.2f}-{max(r_light):.2f} STARTs per pixel per cycle); density "
             f"tests at n = {', '.join(f'{x:.3f}' for x in d_light)}, "
             f"{args.density_cycles:.1e} cycles each (INL from n = {d_light[i_best]:.3f}); "
             f"delay capture {args.delay_cycles:,} cycles at n = {z_light:.2f}; estimator "
             f"{args.estimator}; chip seed {args.chip_seed}. Simulation {t_sim:.0f} s "
             f"(0: cached), calibration and ranging {t_cal:.0f} s.", "",
             "| truth injected | RMS cm | max cm | mean cm | detected | sigma RMS cm | "
             + " | ".join(f"{s} RMS cm" for s in set_names) + " |",
             "|---|---:|---:|---:|---:|---:|" + "---:|" * len(set_names)]
    for name, _, s in rows:
        lines.append(f"| {name} | {s['rms']:.3f} | {s['max']:.2f} | {s['bias']:+.3f} | "
                     f"{s['detected']}/{s['n']} | {s['stat']:.3f} | "
                     + " | ".join(f"{s[k]:.3f}" for k in set_names) + " |")
    lines += budget(rows) + ["", diag]
    emit(lines, args.out)


def diagnostics(base: Calibration, chip, n_density, ranges, r_light, delay_state, z_light,
                args) -> str:
    """The calibration against truth: INL RMS (codes below x_T), the LSB at each range
    capture's light, the delay."""
    from stages.calibration_set import time_axis

    res = base.density
    _, x_t, inl_t = chip.window_truth(n_density, WINDOW_S)
    k = np.arange(inl_t.shape[1])[None, :]
    e = np.where(k < x_t[:, None] - 1, res.inl_lsb - inl_t, np.nan)
    inl_rms = np.sqrt(np.nanmean(e ** 2, axis=1))
    lsb_err = []
    for st, light in zip(ranges, r_light, strict=True):
        axis = time_axis(base, st.hits, st.cycles, WINDOW_S)
        lsb_err.append(WINDOW_S / _x_t_of(axis) * 1e12
                       - chip.window_truth(light, WINDOW_S)[0] * 1e12)
    lsb_err = np.concatenate(lsb_err)
    d = delay_from_state(base, delay_state, WINDOW_S, 140e-9).delay_s
    derr = (d - args.delay_ns * 1e-9) * 1e12
    return (f"Calibration against truth: INL RMS over the window {np.median(inl_rms):.3f} "
            f"LSB median, {np.max(inl_rms):.3f} worst TDC; the window LSB on the range "
            f"captures' axes {np.sqrt(np.mean(lsb_err ** 2)):.3f} ps RMS, "
            f"{np.max(np.abs(lsb_err)):.3f} ps worst; the delay "
            f"{np.sqrt(np.nanmean(derr ** 2)):.1f} ps RMS, {np.nanmax(np.abs(derr)):.1f} ps "
            f"worst (n = {z_light:.2f}).")


def _x_t_of(axis) -> np.ndarray:
    """Where tau = T falls on an axis before it is bounded by the light: T over the scale
    at the polynomial's LSB, read back as an LSB."""
    from stages.calibration_set import _x_t

    return _x_t(axis.tau_edges_s, WINDOW_S)


def budget(rows) -> list[str]:
    """Each cause's share of the RMS: sqrt(RMS^2 with it - RMS^2 without it), the delay
    against the default chain, the others against the true-delay row (the issue's
    setting), one at a time; the estimator's own error split into its predicted
    statistical sigma and the rest."""
    by = {frozenset(c): s for _, c, s in rows}
    base = by.get(frozenset({"delay"}))
    if base is None:
        return []

    def share(a, b):
        d = a["rms"] ** 2 - b["rms"] ** 2
        return np.sign(d) * np.sqrt(abs(d))

    out = ["", "| cause | RMS share cm | how |", "|---|---:|---|"]
    full = by.get(frozenset())
    if full is not None:
        out.append(f"| delay measurement | {share(full, base):.3f} | default chain against "
                   "the true delay |")
    for key, name in (("lsb", "LSB at the capture's light (eq. 5.1 polynomial)"),
                      ("inl", "INL (density test)"), ("sigma", "instrument response sigma")):
        s = by.get(frozenset({"delay", key}))
        if s is not None:
            out.append(f"| {name} | {share(base, s):.3f} | true delay, against true delay + "
                       f"true {key} |")
    est = by.get(frozenset({"delay", "lsb", "inl", "sigma"}))
    if est is not None:
        rest = np.sqrt(max(est["rms"] ** 2 - est["stat"] ** 2, 0.0))
        out.append(f"| estimator: statistics (its sigma) | {est['stat']:.3f} | exact axis, "
                   "true delay and sigma |")
        out.append(f"| estimator: beyond its sigma | {rest:.3f} | the same, less the "
                   "statistics |")
    out.append("(A negative share: that truth made it worse, i.e. errors that cancelled.)")
    return out


if __name__ == "__main__":
    main()
