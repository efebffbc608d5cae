"""Whether the table's sigma covers the time axis between two density tests' levels, one
zoo chip at a time (docs/calibration.md "Between the levels, one chip at a time").

Each chip (``calibration_sigma.chip_of(seed, n)``) is calibrated as ``tcspc calibrate lsb``
does it (``calibration_sigma.calibrate``: four density tests at 0.02-0.3), then a capture
of uniform light between two levels (5e4 cycles) is given its time axis
(``stages.calibration_set.time_axis``); the axis read at the chip's true x_T (where tau =
T) is off by ``err``, against what ``uncertainty.table_sigma_s`` with
``Calibration.scale_refs`` says (``said``: the table's widths and the density tests' own
x_T, ``LsbFit.sigma_ps``): ``z = err / said``, as
``tests/pipeline/offline/test_calibration_sigma.py`` checks on two chips.

Per chip, TDC count and light: z RMS, the share within 2 sigma, the median sigma said, the
error RMS and the worst TDC, with the code that puts most of its error there
(``time_coefficients`` times the table's width error against the chip's truth; "dead" where
that code is one of the chip's dead codes or a neighbour holding its time). Then pooled
per TDC count, and with the scale's spread between the levels added to the sigma
(``cal.scale_spread``, as a range's sigma adds it).

    python benchmarks/calibration_between_levels.py [--seeds 3 4 5 6 7] [--tdcs 8 16]
        [--lights 0.035 0.17]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.calibration_sigma import T, calibrate, capture, chip_of  # noqa: E402
from stages import calibration as cal  # noqa: E402
from stages.calibration import uncertainty  # noqa: E402
from stages.calibration_set import time_axis  # noqa: E402


def between(seed: int, n_tdc: int, lights=(0.035, 0.17)) -> list[dict]:
    """One chip's rows, one a light: the error at the true x_T (s), the sigma said (s),
    and what puts the worst TDC's error where it is."""
    chip = chip_of(seed, n_tdc)
    calib = calibrate(chip, seed)
    rng = np.random.default_rng(seed)  # as the test draws its captures
    truth = np.arange(513.0)[None, :] + chip.inl_lsb
    dead = (np.zeros((n_tdc, 512), bool) if chip.dead_codes is None
            else np.asarray(chip.dead_codes, bool))
    near = dead | np.roll(dead, 1, axis=1) | np.roll(dead, -1, axis=1)
    rows = []
    for light in lights:
        st = capture(chip, light, 5e4, rng)
        axis = time_axis(calib, st.hits, st.cycles, T)
        lt = cal.light_level(st.hits, st.cycles)
        x_t = chip.window_truth(lt, T)[1]
        err = np.array([np.interp(x_t[t], np.arange(513.0), axis.tau_edges_s[t])
                        for t in range(n_tdc)]) - T
        refs = calib.scale_refs(T, lt, axis.source)
        said = uncertainty.table_sigma_s(calib.width_var_lsb2, x_t, axis.x_t, axis.scale, refs)
        # with the scale's spread between the levels (the sqrt(n) and n splines apart,
        # cal.scale_spread), as a range's sigma adds it (its interpolation's bias where
        # the levels leave the LSB's bend unresolved; not the table's)
        spread = cal.scale_spread(calib.density, calib.lsb_fit, T, lt,
                                  calib.scale_splines(T))[0]
        total = np.hypot(said, uncertainty.scale_rel_sigma(spread) * T)
        ok = np.isfinite(err) & np.isfinite(said) & (said > 0)
        z = np.where(ok, err / np.where(ok, said, 1.0), np.nan)
        z_all = np.where(ok, err / np.where(ok, total, 1.0), np.nan)
        w = int(np.nanargmax(np.abs(z)))
        # the worst TDC's error code by code: a_j times the table's width error (the
        # table's widths and the truth's in the units of their sum over codes 20-300)
        a = uncertainty.time_coefficients(x_t[w:w + 1], axis.x_t[w:w + 1],
                                          axis.scale[w:w + 1], None if refs is None else
                                          tuple(r[w:w + 1] for r in refs))[0]
        wh, wt = np.diff(calib.code_bounds[w]), np.diff(truth[w])
        part = a * (wh - wt * wh[20:300].sum() / wt[20:300].sum())
        code = int(np.argmax(np.abs(part)))
        rows.append(dict(seed=seed, n_tdc=n_tdc, light=light, err=err[ok], said=said[ok],
                         z=z[ok], z_all=z_all[ok], worst=w, worst_err=err[w], worst_said=said[w],
                         worst_z=z[w], code=code, code_ps=part[code] * 1e12,
                         code_dead=bool(near[w, code])))
    return rows


def rms(a) -> float:
    return float(np.sqrt(np.mean(np.square(a))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[3, 4, 5, 6, 7])
    ap.add_argument("--tdcs", type=int, nargs="+", default=[8, 16])
    ap.add_argument("--lights", type=float, nargs="+", default=[0.035, 0.17])
    a = ap.parse_args()
    print("| TDCs | chip | light | z RMS | within 2 sigma | median sigma (ps) | error RMS (ps) "
          "| worst TDC: error / sigma (ps), z | its largest code: ps |")
    print("|---|---|---|---|---|---|---|---|---|")
    pooled: dict[int, list] = {n: [] for n in a.tdcs}
    for n in a.tdcs:
        for seed in a.seeds:
            for r in between(seed, n, a.lights):
                pooled[n].append(r)
                print(f"| {n} | {seed} | {r['light']} | {rms(r['z']):.2f} | "
                      f"{np.mean(np.abs(r['z']) <= 2):.3f} | {np.median(r['said']) * 1e12:.1f} | "
                      f"{rms(r['err']) * 1e12:.1f} | t{r['worst']}: {r['worst_err'] * 1e12:.0f} / "
                      f"{r['worst_said'] * 1e12:.1f}, {r['worst_z']:.1f} | {r['code']}"
                      f"{' (dead)' if r['code_dead'] else ''}: {r['code_ps']:.0f} |")
    print()
    for n, rows in pooled.items():
        z = np.concatenate([r["z"] for r in rows])
        per = [rms(r["z"]) for r in rows]
        z_all = np.concatenate([r["z_all"] for r in rows])
        print(f"{n} TDCs, seeds {a.seeds}: {z.size} TDC-captures, z RMS {rms(z):.2f} (per chip "
              f"and light {min(per):.2f}-{max(per):.2f}), within 2 sigma "
              f"{np.mean(np.abs(z) <= 2):.3f}, within 1 sigma {np.mean(np.abs(z) <= 1):.3f}, "
              f"median sigma {np.median(np.concatenate([r['said'] for r in rows])) * 1e12:.1f} "
              f"ps, error RMS {rms(np.concatenate([r['err'] for r in rows])) * 1e12:.1f} ps; "
              f"with the scale's spread: z RMS {rms(z_all):.2f}, within 2 sigma "
              f"{np.mean(np.abs(z_all) <= 2):.3f}")


if __name__ == "__main__":
    main()
