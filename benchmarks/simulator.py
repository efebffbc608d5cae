"""Simulator speed against error: TDC-cycles/s of each engine, and how far its histograms
are from the analytic model of the models issue, across M = 0.01..5 and SBR = 0.01..100.

Each cell simulates 128 identical TDCs for 8192 cycles (1e6 TDC-cycles, words encoded)
and pools their first-START times (arrival order, 0.2 ns bins, plus the reset peak and
"no START") against ``first_photon_histogram``: chi-square p-value and reduced chi-square.
Throughput is measured on the same run, pinned to one core.

    python benchmarks/simulator.py [--out benchmarks/results/simulator.md]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.datapath import emit, machine  # noqa: E402
from stages.models.scene import evaluate, load_scene  # noqa: E402
from stages.models.tcspc import first_photon_histogram  # noqa: E402
from stages.simulator.chip import make_chip  # noqa: E402
from stages.simulator.engines import KIND_PHOTON, Optics  # noqa: E402
from stages.simulator.source import Simulator  # noqa: E402

WINDOW, RESET, SIGMA, TOF, N_TDC, CYCLES = 80e-9, 20e-9, 0.18e-9, 40e-9, 128, 8192
MAX_REFERENCE_PHOTONS = 3e8


def optics(m, sbr):
    bg = m / (sbr * WINDOW)
    return Optics(np.full(N_TDC, m), np.full(N_TDC, TOF), SIGMA, np.full(N_TDC, bg), WINDOW,
                  RESET)


def speed(sim: Simulator, cycles: int) -> float:
    sim.chunk(0, 64)  # compile / warm
    t0 = time.perf_counter()
    for _ in sim.batches(cycles):
        pass
    return cycles * N_TDC / (time.perf_counter() - t0)


def error(sim: Simulator, m, sbr, cycles: int) -> tuple[float, float]:
    bins = np.arange(0, WINDOW + 1e-15, 0.2e-9)
    obs = np.zeros(bins.size)  # window bins + reset
    none = 0
    rng = np.random.default_rng(99)
    done = 0
    while done < cycles:
        n = min(2048, cycles - done)
        st = sim.engine.draw(rng, n) if sim.engine_name == "fast" else sim.engine.draw(rng, n, 0)
        t = st.t_s[st.kind == KIND_PHOTON]
        obs[:-1] += np.histogram(t, bins)[0]
        obs[-1] += np.sum(t < 0)
        none += n * N_TDC - st.index.size
        done += n
    h = first_photon_histogram(m, TOF, SIGMA, m / (sbr * WINDOW), WINDOW, 0.2e-9, RESET)
    p = np.concatenate([h.p, [h.p_reset, h.p_none]])
    o = np.append(obs, none)
    e = p / p.sum() * o.sum()
    small = e < 5
    o = np.concatenate([o[~small], [o[small].sum()]])
    e = np.concatenate([e[~small], [e[small].sum()]])
    if e[-1] == 0:
        o, e = o[:-1], e[:-1]
    res = stats.chisquare(o, e)
    return float(res.pvalue), float(res.statistic / max(o.size - 1, 1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    os.sched_setaffinity(0, {0})
    chip = make_chip(N_TDC, 1, inl_scale=0.0, artifact_rate=0.0)
    lines = [f"command: `python {' '.join(sys.argv)}`", f"machine: {machine()}", "",
             "#### speed against error, 1e6 TDC-cycles per cell (128 TDCs x 8192 cycles)", "",
             "| M | SBR | STARTs per TDC-cycle | engine | M TDC-cycles/s | chi2 p | chi2/dof |",
             "|---:|---:|---:|---|---:|---:|---:|"]
    for m in (0.01, 0.1, 1.0, 5.0):
        for sbr in (0.01, 1.0, 100.0):
            o = optics(m, sbr)
            starts = 1 - float(first_photon_histogram(m, TOF, SIGMA, o.bg_hz[0], WINDOW, 1e-9,
                                                      RESET).p_none)
            for label, kw in (("fast (numba)", dict(engine="fast", compiled=True)),
                              ("fast (numpy)", dict(engine="fast", compiled=False)),
                              ("reference", dict(engine="reference"))):
                sim = Simulator.from_optics(o, chip, 5, spad_sigma_s=0.17e-9, **kw)
                photons = (m + o.bg_hz[0] * (WINDOW + RESET)) * N_TDC * CYCLES
                if kw["engine"] == "reference" and photons > MAX_REFERENCE_PHOTONS:
                    lines.append(f"| {m:g} | {sbr:g} | {starts:.3f} | {label} | skipped: "
                                 f"{photons:.1e} photons | | |")
                    continue
                rate = speed(sim, CYCLES)
                p, red = error(sim, m, sbr, CYCLES) if label != "fast (numpy)" else (None, None)
                cell = "same bytes as numba" if p is None else f"{p:.3f} | {red:.3f}"
                if p is None:
                    cell = "(same words as numba) | "
                lines.append(f"| {m:g} | {sbr:g} | {starts:.3f} | {label} | {rate / 1e6:.1f} | "
                             f"{cell} |")
    lines += ["", "#### shipped scenes (128 TDCs, 40 000 cycles, words encoded)", "",
              "| scene | STARTs per TDC-cycle | fast numba | fast numpy | reference |",
              "|---|---:|---:|---:|---:|"]
    scenes = Path(__file__).resolve().parents[1] / "scenes"
    for name in ("short_range", "long_range", "street", "density", "delay"):
        sm = evaluate(load_scene(scenes / f"{name}.toml"))
        rates = []
        for kw in (dict(engine="fast", compiled=True), dict(engine="fast", compiled=False),
                   dict(engine="reference")):
            sim = Simulator(sm, make_chip(128, 1), 3, **kw)
            rates.append(speed(sim, 40_000) / 1e6)
        lines.append(f"| {name} | {sim.light:.3f} | {rates[0]:.1f} | {rates[1]:.1f} | "
                     f"{rates[2]:.1f} |")
    emit(lines, args.out)


if __name__ == "__main__":
    main()
