"""Where a zoo chip's delay error comes from (issue 33): the delay RMS each part of the
calibration chain costs, before and after the changes of issue 33, and with the density
tests ``calibrate plan`` chooses.

A chip of the zoo with what real chips have (``random_chip(seed, ranges=REAL_CHIP_RANGES)``:
random DNL 0.05-0.1 LSB a code, a bow of 2-4 LSB); four density tests of ``--cycles`` each
at 0.02-0.3 detections a pixel a cycle, and a zero-distance capture dimmer than all of them
(``--zero-light``, its return at code ``--return-code``). The density tests are expected
histograms (:func:`stages.simulator.expected.expected_density_hits`), noise-free or Poisson
draws of them: noise-free, what is left is the method's bias. The delay's error from the
time axis is the axis' error at the return's code at the zero's light; each row substitutes
the truth for one part at a time:

- the INL table (the LSB at the zero's light true): whole, and with the true widths put in
  the codes above the brightest test's window, and past the last code any test measured;
- the LSB(n) interpolation at the zero's light (the table true, the fit's LSB);
- the INL table with the zero capture (``--zero-cycles``, its return at ``--return-code``,
  0.02 a cycle) counted as a fifth density test, as ``calibrate delay`` counts it
  (:mod:`stages.calibration.zero_test`), on the same draws of the tests; the planned
  campaign's row counts the plan's zero capture (2e6 cycles) so too.

The peak's time on the zero capture is not simulated here (its own counting: ~4 ps in the
issue's measurement).

Beside each row, the counting floor (:func:`stages.calibration.floor.tau_floor_s`): the
Cramér-Rao bound on the same error from the same tests' expected counts, whatever the
estimator; a code of the zero's window that no test measured counts the chip's random DNL
as a prior. The rows' floors: the whole table's; what the codes above the brightest test's
window add to it (in quadrature: the floor less the floor with those widths known); what
the codes no test measured add (the prior's part). ``--draws`` noisy campaigns a seed (the
noisy columns' RMS is over all of them: one draw of 8 TDCs is +-15 %).

    python benchmarks/calibration_bias.py [--seeds 1 2 3] [--tdcs 16] [--cycles 1e6]
        [--budget 4e6] [--zero-light 0.01] [--zero-cycles 1e6] [--draws 1] [--what-if]

``--what-if`` prints only the floor, of the fixed captures and of what would lower it (the
zero capture's own uniform light counted as a fifth test, clear of its return; every
test's codes up to its own x_T, not 2.5 below it; more cycles in every test), and exits;
with it, ``--levels`` sets the tests' lights and ``--our-chip`` takes our simulator's chip
(``make_chip(tdcs, seed)``, random DNL 0.04 LSB) for the zoo's:
``--our-chip --seeds 4 --levels 0.02 0.06 0.15 0.3 0.5 0.75 --cycles 4e6 --zero-light 0.52
--return-code 300`` is ``benchmarks/range_accuracy.py``'s campaign and delay.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stages import calibration as cal  # noqa: E402
from stages.calibration import uncertainty, zero_test  # noqa: E402
from stages.calibration.floor import tau_floor_s  # noqa: E402
from stages.simulator.chip import REAL_CHIP_RANGES, random_chip  # noqa: E402
from stages.simulator.expected import expected_density_hits, expected_hits  # noqa: E402

T = 80e-9
LEVELS = (0.02, 0.05, 0.1, 0.3)
#: the method before issue 33, and after
METHODS = {"before": {"PHASE_PULL": "window", "OWN_TOP": False, "CONTINUE_CODES": 10**6},
           "after": {"PHASE_PULL": "", "OWN_TOP": True, "CONTINUE_CODES": 64}}


def use(method: str) -> None:
    for name, value in METHODS[method].items():
        setattr(cal, name, value)


def campaign(chip, lights, cycles, rng, zero=None):
    """The INL test (the brightest, filled and combined from the others), the LSB fit, the
    tests' own results and the table's width variance; with ``zero`` (``(light, cycles,
    code)``), the zero capture's uniform light combined into the table as ``calibrate
    delay`` does it (:func:`with_zero`)."""
    c = [np.full(chip.n_tdc, float(n)) for n in cycles]
    hits = [expected_density_hits(chip, n, k[0], T) for n, k in zip(lights, c, strict=True)]
    if rng is not None:
        hits = [rng.poisson(h).astype(np.float64) for h in hits]
    res = [cal.density_test(h, k, T) for h, k in zip(hits, c, strict=True)]
    i = int(np.argmax(lights))
    tests = [(res[j], cal.width_variance(hits[j], c[j], res[j])) for j in range(len(lights))
             if j != i]
    fill = cal.fill_from(tests, res[i])
    best = cal.density_test(hits[i], c[i], T, fill=fill, combine=True)
    n = np.array([float(np.mean(r.detections_per_cycle)) for r in res])
    fit = cal.fit_lsb(n, np.column_stack([r.lsb_s * 1e12 for r in res]))
    var = uncertainty.table_var(best.width_lsb, cal.width_variance(hits[i], c[i], res[i]),
                                fill[1])
    if zero is not None:
        best, var, _ = with_zero(chip, best, var, *zero, rng)
    return best, fit, res, var


#: The zero capture's return (detections a cycle) and pulse in :func:`with_zero`.
ZERO_SIGNAL, ZERO_PULSE_S = 0.02, 150e-12


def with_zero(chip, best, var, light, cycles, code, rng=None):
    """``best`` (a table, ``var`` its width variance) with a zero capture of ``cycles`` at
    ``light`` (its return at ``code``, ``ZERO_SIGNAL`` a cycle) combined in
    (:mod:`stages.calibration.zero_test`, as ``calibrate delay`` does): noise-free, or a
    Poisson draw with ``rng``. The return is located as the largest count within 20 codes
    of ``code``, its mask from the pulse's width. Returns the table, its variance and the
    codes the capture added to per TDC."""
    lsb = chip.window_truth(light, T)[0]
    z = expected_hits(chip, light, cycles, T, signal=np.full(chip.n_tdc, ZERO_SIGNAL),
                      tau_s=(code + 0.5) * lsb, pulse_sigma_s=ZERO_PULSE_S)
    if rng is not None:
        z = rng.poisson(z).astype(np.float64)
    peak = code - 20 + np.argmax(z[:, code - 20:code + 21], axis=1).astype(np.float64)
    k = np.full(chip.n_tdc, float(cycles))
    zres, zvar = zero_test.zero_density(z, k, T, zero_test.return_mask(peak, ZERO_PULSE_S / lsb))
    return zero_test.with_test(best, var, zres, zvar)


def axis_error_ps(chip, best, n0, code, lsb_s=None, bounds=None):
    """The time axis' error at boundary ``code`` at light ``n0`` (per TDC, ps)."""
    lsb_w = chip.window_truth(n0, T)[0] if lsb_s is None else lsb_s
    b = cal.code_bounds(best) if bounds is None else bounds
    tau = b * cal.scale_at_light(best, lsb_w, T, bounds=b)[:, None]
    return (tau - chip.boundaries_s(n0))[:, code] * 1e12


def with_true_widths(chip, best, light, codes_from):
    """``best``'s boundaries with the chip's widths (at ``light``, in its units) from code
    ``codes_from`` (per TDC) on."""
    lsb, x, inl = chip.window_truth(light, T)
    b = cal.code_bounds(best)
    true = chip.boundaries_s(light) / lsb[:, None]
    k = np.arange(513)[None, :]
    start = np.clip(np.asarray(codes_from, int), 1, 512)[:, None]
    at = np.take_along_axis(b, start, axis=1) - np.take_along_axis(true, start, axis=1)
    return np.where(k >= start, true + at, b)


#: The row of the table with the zero capture counted as a fifth test.
ZERO_ROW = "INL table, the zero capture a fifth density test"


def rows_for(chip, lights, cycles, n0, code, rng, zero_cycles=None):
    best, fit, res, var = campaign(chip, lights, cycles, rng)
    bright = res[int(np.argmax(lights))]
    out = {"INL table": axis_error_ps(chip, best, n0, code)}
    if zero_cycles:
        out[ZERO_ROW] = axis_error_ps(chip, with_zero(chip, best, var, n0, zero_cycles, code,
                                                      rng)[0], n0, code)
    above = np.floor(bright.x_t - cal.EDGE_MARGIN - 1)
    out["  codes above the brightest test's window (true there)"] = out["INL table"] - \
        axis_error_ps(chip, best, n0, code, bounds=with_true_widths(
            chip, best, float(np.mean(bright.detections_per_cycle)), above))
    last = np.array([np.flatnonzero(np.isfinite(r))[-1] + 1 for r in best.inl_lsb])
    out["  table past the last measured code (true there)"] = out["INL table"] - \
        axis_error_ps(chip, best, n0, code, bounds=with_true_widths(
            chip, best, float(np.mean(bright.detections_per_cycle)), last))
    true_b = with_true_widths(chip, best, float(np.mean(bright.detections_per_cycle)),
                              np.zeros(chip.n_tdc))
    out["LSB(n) at the zero's light (table true)"] = scale_error_ps(chip, best, fit, n0, code,
                                                                    true_b)
    return out


def scale_error_ps(chip, best, fit, n0, code, bounds):
    """The time axis' error at boundary ``code`` at light ``n0`` (per TDC, ps) when the
    scale is read as the chain reads it inside the levels (:func:`cal.scale_at_light`: each
    test's scale ``T / B(T / LSB_i)``, a spline in sqrt(n)), on ``bounds``. (Reading the
    LSB's own spline instead carries the INL's ripple in the window LSB: 16.9 ps against
    3.0 at 0.07 on seeds 6-8, noise-free, a cost the chain does not pay.)"""
    from scipy.interpolate import CubicSpline

    from stages.calibration.timescale import _bound_at

    lv = np.asarray(fit.levels, np.float64)
    o = np.argsort(lv)
    pts = fit.points_ps()[:, o] * 1e-12
    s = np.column_stack([T / _bound_at(bounds, T / pts[:, j]) for j in range(lv.size)])
    if not lv[o][0] <= n0 <= lv[o][-1]:  # outside the levels the chain uses eq. 5.1's cubic
        return axis_error_ps(chip, best, n0, code, lsb_s=fit.cubic_ps(n0) * 1e-12,
                             bounds=bounds)
    scale = CubicSpline(np.sqrt(lv[o]), s.T, axis=0)(np.sqrt(n0))
    return (bounds[:, code] * scale - chip.boundaries_s(n0)[:, code]) * 1e12


def floor_rows(chip, knobs, lights, cycles, n0, code, zero_cycles=None):
    """The counting floor (ps per TDC) of the rows of :func:`rows_for` that have one."""
    n_tdc = chip.n_tdc
    tests = [(expected_density_hits(chip, n, k, T), np.full(n_tdc, float(k)),
              chip.window_truth(n, T)[1]) for n, k in zip(lights, cycles, strict=True)]
    widths = np.diff(chip.boundaries_s(n0), axis=1)
    x_t0 = chip.window_truth(n0, T)[1]
    sd = float(knobs.get("dnl_random_lsb", 0.1))

    def floor(**kw):
        return tau_floor_s(tests, widths, code, x_t0, T, **kw) * 1e12

    whole = floor(unmeasured_sd=sd)
    bright = tests[int(np.argmax(lights))][2]
    above = floor(unmeasured_sd=0, known_from=np.floor(bright - cal.OWN_CLEAR_LSB))
    counted = floor(unmeasured_sd=0)
    more = {}
    if zero_cycles:
        lsb = chip.window_truth(n0, T)[0]
        z = expected_hits(chip, n0, zero_cycles, T, signal=np.full(n_tdc, ZERO_SIGNAL),
                          tau_s=(code + 0.5) * lsb, pulse_sigma_s=ZERO_PULSE_S)
        x_z = chip.window_truth(cal.light_level(z, np.full(n_tdc, zero_cycles)), T)[1]
        clear = ~zero_test.return_mask(np.full(n_tdc, float(code)), ZERO_PULSE_S / lsb)
        tests = tests + [(z, np.full(n_tdc, float(zero_cycles)), x_z, clear)]
        more[ZERO_ROW] = floor(unmeasured_sd=sd)
    return {"INL table": whole, **more,
            "  codes above the brightest test's window (true there)":
                np.sqrt(np.maximum(whole ** 2 - above ** 2, 0.0)),
            "  table past the last measured code (true there)":
                np.sqrt(np.maximum(whole ** 2 - counted ** 2, 0.0))}


def what_if(a) -> None:
    """The floor of the fixed captures and of what would lower it (``--what-if``)."""
    out: dict = {}
    from stages.simulator.chip import make_chip

    for seed in a.seeds:
        chip, knobs = ((make_chip(a.tdcs, seed), {"dnl_random_lsb": 0.04}) if a.our_chip
                       else random_chip(seed, n_tdc=a.tdcs, ranges=REAL_CHIP_RANGES))
        n_tdc, n0 = chip.n_tdc, a.zero_light
        tests = [(expected_density_hits(chip, n, a.cycles, T), np.full(n_tdc, a.cycles),
                  chip.window_truth(n, T)[1]) for n in a.levels]
        widths = np.diff(chip.boundaries_s(n0), axis=1)
        lsb, x_t0, _ = chip.window_truth(n0, T)

        def floor(tt, x_t0=x_t0, widths=widths, knobs=knobs, margin=cal.OWN_CLEAR_LSB):
            return tau_floor_s(tt, widths, a.return_code, x_t0, T, margin=margin,
                               unmeasured_sd=float(knobs["dnl_random_lsb"])) * 1e12

        out.setdefault("the fixed captures", []).append(floor(tests))
        # (issue 33, point 2) every code up to each test's own x_T counted as uniform
        # light: what the codes under the reset peak's tail could add at most
        for m in (1.0, 0.0):
            out.setdefault(f"the fixed captures, each test's codes up to {m:g} below its "
                           "x_T (the reset peak's tail taken as known)", []).append(
                floor(tests, margin=m))
        # ... and a bound on what those codes can add whatever the model of the reset peak:
        # the codes under every test's reset peak (2.5 below to 2 above its x_T) known
        # exactly (an oracle test of 1e9 counts a code there, its own light free)
        k = np.arange(512)[None, :]
        peak = np.zeros((n_tdc, 512), bool)
        for _, _, xt in tests:
            peak |= (k + 1 > xt[:, None] - cal.OWN_CLEAR_LSB) & (k < xt[:, None] + 2)
        oracle = (np.where(peak, 1e9, 0.0), np.full(n_tdc, 1e12), np.full(n_tdc, 600.0), peak)
        out.setdefault("the fixed captures, the codes under every test's reset peak known "
                       "exactly", []).append(floor(tests + [oracle]))
        # the return masked as `calibrate delay` masks it (zero_test.return_mask)
        clear = ~zero_test.return_mask(np.full(n_tdc, float(a.return_code)),
                                       ZERO_PULSE_S / lsb)
        for zc in (1e6, 2e6):
            z = expected_hits(chip, n0, zc, T, signal=np.full(n_tdc, ZERO_SIGNAL),
                              tau_s=(a.return_code + 0.5) * lsb, pulse_sigma_s=ZERO_PULSE_S)
            # its window ends where its own light (the return's STARTs too) puts x_T
            x_z = chip.window_truth(cal.light_level(z, np.full(n_tdc, zc)), T)[1]
            five = tests + [(z, np.full(n_tdc, zc), x_z, clear)]
            out.setdefault(f"+ the zero's own light, {zc:.0e} cycles (return "
                           f"{ZERO_SIGNAL} a cycle)", []).append(floor(five))
            if zc == 1e6:
                out.setdefault("+ the zero's own light, 1e+06 cycles, every test's codes up "
                               "to its x_T", []).append(floor(five, margin=0.0))
        for x in (1.5, 1.7, 2.0):
            out.setdefault(f"every test's cycles x{x}", []).append(
                floor([(h * x, c * x, xt) for h, c, xt in tests]))
    print(f"Counting floor of the delay (ps RMS), {'our' if a.our_chip else 'zoo'} chip "
          f"seeds {a.seeds}, {a.tdcs} TDCs, tests at {tuple(a.levels)} x {a.cycles:.0e} "
          f"cycles, zero at {a.zero_light}, return at code {a.return_code}:")
    for name, v in out.items():
        print(f"  {name}: {rms(v):.1f}")


def rms(v):
    v = np.concatenate(v)
    return float(np.sqrt(np.nanmean(v ** 2)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--tdcs", type=int, default=16)
    ap.add_argument("--cycles", type=float, default=1e6)
    ap.add_argument("--budget", type=float, default=4e6)
    ap.add_argument("--zero-light", type=float, default=0.01)
    ap.add_argument("--return-code", type=int, default=200)
    ap.add_argument("--draws", type=int, default=1)
    ap.add_argument("--zero-cycles", type=float, default=1e6,
                    help="the zero capture's cycles, for the row that counts it as a fifth "
                         "density test (0: no such row)")
    ap.add_argument("--what-if", action="store_true")
    ap.add_argument("--levels", type=float, nargs="+", default=list(LEVELS))
    ap.add_argument("--our-chip", action="store_true")
    a = ap.parse_args()
    if a.what_if:
        what_if(a)
        return
    table: dict = {}
    floors: dict = {}
    for seed in a.seeds:
        chip, knobs = random_chip(seed, n_tdc=a.tdcs, ranges=REAL_CHIP_RANGES)
        for name, v in floor_rows(chip, knobs, LEVELS, [a.cycles] * len(LEVELS),
                                  a.zero_light, a.return_code, a.zero_cycles).items():
            floors.setdefault(name, []).append(v)
    for method in METHODS:
        use(method)
        for noisy in (False, True):
            for seed in a.seeds:
                chip, _ = random_chip(seed, n_tdc=a.tdcs, ranges=REAL_CHIP_RANGES)
                for d in range(a.draws if noisy else 1):
                    rng = (None if not noisy else np.random.default_rng(seed) if d == 0
                           else np.random.default_rng([seed, d]))
                    rows = rows_for(chip, LEVELS, [a.cycles] * len(LEVELS), a.zero_light,
                                    a.return_code, rng, a.zero_cycles)
                    for name, v in rows.items():
                        table.setdefault(name, {}).setdefault((method, noisy), []).append(v)
    # the planned campaign, after: the same budget as calibrate plan spends it
    use("after")
    planned = {False: [], True: []}
    planned_floor = []
    for seed in a.seeds:
        chip, knobs = random_chip(seed, n_tdc=a.tdcs, ranges=REAL_CHIP_RANGES)
        zero = expected_density_hits(chip, a.zero_light, 2e6, T)
        k = np.arange(a.return_code - 10, a.return_code + 11)
        zero[:, k] += 2e6 * 0.002 * np.exp(-0.5 * ((k - a.return_code) / 1.5) ** 2)[None] / 3.76
        zero = np.random.default_rng(seed).poisson(zero)
        plan = cal.plan_tests(zero, np.full(a.tdcs, 2e6), a.budget, T)
        # the plan counts the zero capture's own counts (plan_tests(zero_as_test=True)),
        # and calibrate delay combines them: the row does too (its 2e6 cycles)
        planned_floor.append(floor_rows(chip, knobs, list(plan.lights), list(plan.cycles),
                                        a.zero_light, a.return_code, 2e6)[ZERO_ROW])
        for noisy in (False, True):
            for d in range(a.draws if noisy else 1):
                rng = (None if not noisy else np.random.default_rng(seed) if d == 0
                       else np.random.default_rng([seed, d]))
                planned[noisy].append(rows_for(chip, list(plan.lights), list(plan.cycles),
                                               a.zero_light, a.return_code, rng,
                                               2e6)[ZERO_ROW])
        print(f"seed {seed}: plan {[(round(float(n), 4), int(c)) for n, c in zip(plan.lights, plan.cycles, strict=True)]}, "  # noqa: E501
              f"expected {np.nanmedian(plan.delay_error_ps):.0f} ps")
    print(f"\nDelay RMS (ps) each part costs, real-chip zoo seeds {a.seeds}, {a.tdcs} TDCs, "
          f"tests at {LEVELS} x {a.cycles:.0e} cycles, zero at {a.zero_light}, return at code "
          f"{a.return_code}, {a.draws} noisy draw(s) a seed\n")
    print("| part of the chain | before, noise-free | before, noisy | after, noise-free "
          "| after, noisy | counting floor |")
    print("|---|---|---|---|---|---|")
    for name, cols in table.items():
        fl = f"{rms(floors[name]):.1f}" if name in floors else ""
        print(f"| {name} | " + " | ".join(f"{rms(cols[(m, n)]):.1f}" for m in METHODS
                                          for n in (False, True)) + f" | {fl} |")
    print(f"| INL table, the {a.budget:.0e} cycles as `calibrate plan` spends them (and the "
          f"zero capture's 2e6 counted) | | | "
          f"{rms(planned[False]):.1f} | {rms(planned[True]):.1f} | {rms(planned_floor):.1f} |")
    print("\nper seed, the INL table after (noisy) against its floor (ps RMS over the TDCs):")
    k = len(a.seeds)
    after = table["INL table"][("after", True)]
    for i, seed in enumerate(a.seeds):
        mine = after[i * a.draws:(i + 1) * a.draws]
        print(f"  seed {seed}: {rms(mine):.1f} measured, floor {rms([floors['INL table'][i]]):.1f}")
    assert len(after) == k * a.draws


if __name__ == "__main__":
    main()
