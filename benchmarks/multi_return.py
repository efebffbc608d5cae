"""Two surfaces a pixel (a window, a fence): detection and range error of the returns
against their separation and against the weaker surface's share of the counts.

Each cell draws 200 first-photon histograms of two Gaussian returns from the exact model
(``stages.ranging_eval.two_surfaces``: 0.1 ns bins, instrument sigma 0.2 ns, 1 background
count a bin, 1e5 cycles: little pile-up) and ranges them with up to 3 returns a pixel
(``stages.ranging.estimate_returns``, p_fa 1e-3). Separations are in instrument widths
(FWHM = 2.355 sigma = 0.47 ns). Sweep 1: separation 0.5 .. 5 widths, the weaker with 30 %
of 1 000 signal counts (300). Sweep 2: at 3 widths, the weaker's share 0.1 .. 0.5 of
1 000. Then background-only histograms: the share of pixels with any detected return.

    python benchmarks/multi_return.py [--pixels 200] [--estimators fast,ml] [--out FILE]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from scipy.constants import c as C

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.datapath import emit, machine  # noqa: E402
from stages.ranging import Histograms, estimate_returns  # noqa: E402
from stages.ranging_eval import score_returns, two_surfaces  # noqa: E402

SIGMA, BIN, P_FA = 0.2e-9, 0.1e-9, 1e-3


def cell(estimator: str, sep: float, share: float, total: float, n_pix: int, seed: int):
    rng = np.random.default_rng(seed)
    h, truth = two_surfaces(rng, n_pix, sep, share, total, SIGMA, BIN)
    t0 = time.perf_counter()
    est = estimate_returns(h, SIGMA, estimator, P_FA, 3)
    dt = time.perf_counter() - t0
    return {"estimator": estimator, "sep": sep, "share": share,
            "weak_counts": share * total, **score_returns(est, truth),
            "hist_per_s": n_pix / dt}


def row(r: dict) -> str:
    def f(key, fmt):
        return format(r[key], fmt) if key in r else "-"
    return (f"| {r['estimator']} | {r['sep']:g} | {r['share']:.0%} ({r['weak_counts']:.0f}) | "
            f"{r['both_detected']:.1%} | {r['weaker_detected']:.1%} | "
            f"{f('near_bias_ps', '+.1f')} / {f('near_rms_ps', '.1f')} / "
            f"{f('near_sigma_ps', '.1f')} | {f('near_cover_2sigma', '.0%')} | "
            f"{f('far_bias_ps', '+.1f')} / {f('far_rms_ps', '.1f')} / "
            f"{f('far_sigma_ps', '.1f')} | {f('far_cover_2sigma', '.0%')} | "
            f"{r['hist_per_s']:,.0f} |")


HEAD = ["| estimator | separation (widths) | weaker share (counts) | both detected | "
        "weaker detected | near: bias / RMS / sigma (ps) | near within 2 sigma | "
        "far: bias / RMS / sigma (ps) | far within 2 sigma | histograms/s |",
        "|---|---|---|---|---|---|---|---|---|---|"]


# --- real responses: two-surface histograms from pairs of TMF8820 captures -----------------

TMF = Path(__file__).resolve().parents[1] / "tests" / "data" / "tmf8820"
REAL_SEPS = (0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0)
REAL_SHARES = (0.1, 0.2, 0.3, 0.5)
#: the nearest capture a pair takes (m)
NEAREST = 0.10


def _shift(y: np.ndarray, by: np.ndarray) -> np.ndarray:
    """Each row of ``y`` (counts a bin) moved later by ``by`` bins (fractional: its
    cumulative sum interpolated, so the total is kept)."""
    n = y.shape[1]
    cum = np.concatenate([np.zeros((y.shape[0], 1)), np.cumsum(y, axis=1)], axis=1)
    x = np.arange(n + 1)[None, :] - np.asarray(by, np.float64)[:, None]
    return np.diff(np.array([np.interp(xi, np.arange(n + 1), ci) for xi, ci in
                             zip(x, cum, strict=True)]), axis=1)


def pair_counts(a, b, cycles: float, keep_a, keep_b, align_bins: float, rng):
    """Two captures' zones in one histogram (each a real return with its real tail, noise,
    background and crosstalk): the raw counts thinned binomially (``keep_a``, ``keep_b``
    per zone), Coates-corrected with the calibration's effective pulses ``cycles``, ``b``
    moved by ``align_bins`` (its reference channel onto ``a``'s: the laser's drift between
    the captures), added in the intensity domain and piled up again with the same pulses
    (each bin's expected first-photon count, rounded). Returns the counts (zones + ``a``'s
    reference row), ``a``'s reference last."""
    def corrected(c, keep):
        # a dimmer source: the thinned counts over ``keep`` corrected for the capture's own
        # pile-up (its pulses), times ``keep``: the intensity scaled, with the thinned
        # counts' Poisson noise
        keep = np.clip(keep, 1e-12, 1)[:, None]
        c = rng.binomial(c.astype(np.int64), keep) / keep
        h = Histograms(c, np.tile(np.arange(c.shape[1] + 1.0), (c.shape[0], 1)),
                       np.full(c.shape[0], cycles), np.ones(c.shape, bool))
        return h.intensity() * cycles * keep
    za, zb = ~a.reference, ~b.reference
    lam = (corrected(a.counts[za], keep_a)
           + np.clip(_shift(corrected(b.counts[zb], keep_b), np.full(za.sum(), align_bins)),
                     0, None)) / cycles
    out = np.empty_like(lam)
    risk = np.full(lam.shape[0], float(cycles))
    for j in range(lam.shape[1]):  # the first-photon histogram of the summed intensity
        out[:, j] = np.rint(risk * -np.expm1(-lam[:, j]))
        risk = risk - out[:, j]
    return np.vstack([out, a.counts[a.reference]])


def real_pairs(estimators=("ml",), seed: int = 7) -> list[str]:
    """Detection and range error of two real surfaces against separation and share, the
    extra returns on single captures; a Markdown section."""
    import tempfile

    import polars as pl

    from pipeline.io.generic import read_generic
    from pipeline.io.tmf8820 import convert
    from pipeline.offline import generic as g
    from stages.ranging.irf import _fwhm_bins, fit_response

    tmp = Path(tempfile.mkdtemp(prefix="tmf-pairs-"))
    convert(TMF / "distance_data_even.json", tmp / "h.parquet", tmp / "truth.csv")
    truth = {k[0]: v for k, v in g.read_truth(tmp / "truth.csv").items()}
    names = list(truth)
    cal_names = [min(names, key=lambda n, x=x: abs(truth[n] - x)) for x in (0.1, 0.2, 0.3)]
    (tmp / "cal.csv").write_text("measurement,distance_m\n" + "".join(
        f"{n},{truth[n]}\n" for n in cal_names))
    cal = g.calibrate_distance(tmp / "h.parquet", tmp / "cal.csv")
    meas = {m.name: m for m in read_generic(tmp / "h.parquet")}
    scale = np.nanmean(cal.fits["ml"]["bin_width_ps"]) / cal.nominal_bin_ps
    width_m = _fwhm_bins(cal.returns_response) * cal.nominal_bin_ps * 1e-12 * scale * C / 2
    # each capture's reference time and zones' signal (for the shares), by one ml fit
    ref_t, signal = {}, {}
    for name, m in meas.items():
        cyc = g._cycles(m, cal.cycles)[0]
        ref = fit_response(g._histograms(m, cyc, np.flatnonzero(m.reference)), cal.response,
                           "ml")
        ref_t[name] = float(ref.t_s[0]) / (m.bin_width_s)
        tm = g.measurement_times(m, "ml", P_FA, cal.response, cal.response.sigma_s, cal.cycles)
        signal[name] = np.asarray(tm.est.signal_counts, float)
    # from 0.10 m: nearer, a zone's counts reach the effective pulses (the correction of a
    # thinned capture then amplifies its late bins' noise into spikes that no sum has)
    usable = sorted((n for n in names if n not in cal_names and truth[n] >= NEAREST - 1e-9),
                    key=truth.get)
    rng = np.random.default_rng(seed)

    def cell(sep_w, share, weak_counts=None):
        """Every pair of usable captures ``sep_w`` widths apart (within 2.5 mm): the far
        one the weaker with ``share`` of the two returns' signal (or ``weak_counts``)."""
        rows, truths = [], []
        for a in usable:
            want = truth[a] + sep_w * width_m
            b = min(usable, key=lambda n: abs(truth[n] - want))
            if abs(truth[b] - want) > 2.5e-3 or b == a:
                continue
            sa, sb = signal[a], signal[b]
            target = share / (1 - share) * sa            # the far one's signal wanted
            keep_b = np.minimum(target / sb, 1.0)
            keep_a = np.where(target > sb, sb * (1 - share) / share / sa, 1.0)
            if weak_counts is not None:                  # both thinned: the weaker's counts
                f = weak_counts / (keep_b * sb)
                keep_a, keep_b = keep_a * f, keep_b * f
            counts = pair_counts(meas[a], meas[b], cal.cycles, keep_a, keep_b,
                                 ref_t[a] - ref_t[b], rng)
            rows.append((f"{a}+{b}", counts))
            truths.append((truth[a], truth[b], float(np.median(keep_b * sb))))
        return rows, truths

    def score(rows, truths, estimator):
        m0 = meas[usable[0]]
        n_rows = sum(c.shape[0] for _, c in rows)
        table = pa.table({
            "measurement": [n for n, c in rows for _ in range(c.shape[0])],
            "tdc": pa.array([t for _, c in rows for t in range(c.shape[0])], pa.uint16()),
            "counts": [r.astype(np.int64).tolist() for _, c in rows for r in c],
            "cycles": pa.array([int(cal.cycles)] * n_rows, pa.uint64()),
            "instrument": ["generic"] * n_rows, "bin_width_ps": [m0.bin_width_s * 1e12] * n_rows,
            "reference": [t == c.shape[0] - 1 for _, c in rows for t in range(c.shape[0])]})
        pq.write_table(table, tmp / "pairs.parquet")
        t0 = time.perf_counter()
        r, _ = g.range_generic(tmp / "pairs.parquet", cal, estimator=estimator, max_returns=3)
        dt = time.perf_counter() - t0
        df = pl.from_arrow(r).filter(pl.col("detected"))
        tr = dict(zip([n for n, _ in rows], truths, strict=True))
        both, extra, err, cover, n_pix = 0, 0, [], [], 0
        for name, _ in rows:
            for tdc in range(9):
                n_pix += 1
                grp = df.filter((pl.col("measurement") == name) & (pl.col("tdc") == tdc))
                d, s = grp["distance_m"].to_numpy(), grp["sigma_m"].to_numpy()
                near, far = tr[name][:2]
                hit = [np.argmin(np.abs(d - x)) if d.size else -1 for x in (near, far)]
                ok = [h >= 0 and abs(d[h] - x) < width_m / 2 for h, x in zip(hit, (near, far),
                                                                              strict=True)]
                if all(ok) and hit[0] != hit[1]:
                    both += 1
                    e = [d[hit[0]] - near, d[hit[1]] - far]
                    err.append(e)
                    cover.append([abs(e[0]) < 2 * s[hit[0]], abs(e[1]) < 2 * s[hit[1]]])
                    extra += d.size - 2
                else:
                    extra += max(d.size - sum(ok), 0)
        out = {"pairs": len(rows), "pixels": n_pix, "both": both / max(n_pix, 1),
               "extra": extra, "hist_per_s": n_pix / dt,
               "weak": float(np.median([t[2] for t in truths])) if truths else np.nan}
        if err:
            e, c = np.array(err) * 1e3, np.array(cover)
            for k, nm in ((0, "near"), (1, "far")):
                out[nm] = (f"{np.mean(e[:, k]):+.2f} / {np.sqrt(np.mean(e[:, k] ** 2)):.2f} / "
                           f"{np.mean(c[:, k]):.0%}")
        return out

    head = ["| estimator | separation (widths) | weaker share | weaker's counts (median) | "
            "pairs x zones | both detected | near: bias / RMS mm / within 2 sigma | "
            "far: bias / RMS mm / within 2 sigma | other returns | histograms/s |",
            "|---|---|---|---|---|---|---|---|---|---|"]

    def line(est, sep, share, r):
        return (f"| {est} | {sep:g} | {share:.0%} | {r['weak']:,.0f} | {r['pairs']} x 9 | "
                f"{r['both']:.1%} | {r.get('near', '-')} | {r.get('far', '-')} | "
                f"{r['extra']} | {r['hist_per_s']:,.0f} |")

    lines = ["### Real responses: pairs of TMF8820 captures", "",
             f"calibrated on {', '.join(cal_names)} ({cal.pileup}); the found returns' model: "
             f"{cal.returns_response.source}; a width (its FWHM) = {width_m * 1e3:.1f} mm; "
             f"pairs of the {len(usable)} other captures at {NEAREST:g}-0.40 m, p_fa {P_FA:g}, up "
             "to 3 returns", "", "#### against separation (the far surface 30 %)", "", *head]
    for est in estimators:
        for sep in REAL_SEPS:
            lines.append(line(est, sep, 0.3, score(*cell(sep, 0.3), est)))
    lines += ["", "#### against the weaker's share (3 widths apart)", "", *head]
    for est in estimators:
        for share in REAL_SHARES:
            lines.append(line(est, 3.0, share, score(*cell(3.0, share), est)))
    lines += ["", "#### against the weaker's counts (3 widths apart, 30 %: both captures "
              "thinned, background with them)", "", *head]
    for est in estimators:
        for weak in (200, 1000, 10000):
            lines.append(line(est, 3.0, 0.3, score(*cell(3.0, 0.3, weak), est)))
    # single captures: every further return is a false one (or the scene's own)
    lines += ["", "#### single captures (one flat target): further returns", "",
              "| estimator | captures x zones | further returns | left out at the zero "
              "(crosstalk) | first return RMS mm, K = 1 / K = 3 (>= 5 cm, not calibration) | "
              "histograms/s, K = 1 / K = 3 (reference rows included) |",
              "|---|---|---|---|---|---|"]
    for est in estimators:
        rms, speed = [], []
        for k in (1, 3):
            t0 = time.perf_counter()
            r, info = g.range_generic(tmp / "h.parquet", cal, estimator=est, max_returns=k)
            speed.append(len(meas) * 10 / (time.perf_counter() - t0))
            df = pl.from_arrow(r).with_columns(pl.col("measurement").replace_strict(truth)
                                               .alias("truth_m"))
            first = df.filter((pl.col("return_index") == 0) & (pl.col("truth_m") >= 0.05 - 1e-9)
                              & ~pl.col("measurement").is_in(cal_names))
            rms.append(float(np.sqrt((((first["distance_m"] - first["truth_m"]) * 1e3) ** 2)
                                     .mean())))
        further = df.filter(pl.col("return_index") > 0)
        where = "; ".join(f"{x['measurement']} zone {x['tdc']}: {x['distance_m']:.3f} m "
                          f"behind a target at {x['truth_m']:.3f} m, "
                          f"{x['signal_counts']:.0f} counts" for x in further.to_dicts())
        n_x = info.get("crosstalk", "0").split(" ")[0]
        lines.append(f"| {est} | {df.filter(pl.col('return_index') == 0).height} | "
                     f"{further.height}{' (' + where + ')' if where else ''} | {n_x} | "
                     f"{rms[0]:.3f} / {rms[1]:.3f} | {speed[0]:,.0f} / {speed[1]:,.0f} |")
    return lines + ["", *hydraharp(estimators)]


def hydraharp(estimators=("ml",)) -> list[str]:
    """Further returns on the HydraHarp T3 sample (a fluorescence decay, one return a
    channel, its tail exponential): Gaussian masks against its own response, measured on
    the data (every channel's strongest return aligned and averaged)."""
    from pipeline.offline.instruments import _uniform, histogram_ptu
    from stages.ranging import estimate, response_from_data
    from stages.ranging.irf import response_from_returns

    ptu = TMF.parent / "picoquant" / "hydraharp_v20_t3.ptu"
    table, _ = histogram_ptu(str(ptu), None)
    h = _uniform(table, None)
    sigma = response_from_data(h)[0]
    lines = ["#### the HydraHarp T3 sample (tests/data/picoquant): further returns a channel",
             "", "| estimator | model of a found return | channels | further returns "
             "(behind the first, m) |", "|---|---|---|---|"]
    for est in estimators:
        first = estimate(h, sigma, est, P_FA)
        resp = response_from_returns(h, np.where(first.detected, first.t_s, np.nan),
                                     "the channels' strongest returns, aligned and averaged")
        for how, kw in (("Gaussian masks", {}), ("measured on the data", {"response": resp,
                                                                         "first": first})):
            r = estimate_returns(h, sigma, est, P_FA, 3, **kw)
            more = (r.return_index > 0) & r.detected
            behind = [f"{(t - first.t_s[p]) * C / 2:.2f}" for t, p in
                      zip(r.t_s[more], r.pixel[more], strict=True)]
            lines.append(f"| {est} | {how} | {h.counts.shape[0]} | {int(more.sum())}"
                         + (f" ({', '.join(behind)})" if behind else "") + " |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pixels", type=int, default=200)
    ap.add_argument("--estimators", default="fast,ml")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--only", choices=("simulated", "real"), default=None,
                    help="one part only (default both)")
    args = ap.parse_args()
    ests = args.estimators.split(",")
    head = [f"command: `python {' '.join(sys.argv)}`", f"machine: {machine()}", ""]
    if args.only == "real":
        emit(head + real_pairs(tuple(ests)), args.out)
        return
    lines = [*head,
             f"#### against separation (weaker 30 % of 1 000 counts), {args.pixels} "
             "pixels a cell", "", *HEAD]
    for est in ests:
        for i, sep in enumerate((0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0)):
            lines.append(row(cell(est, sep, 0.3, 1000.0, args.pixels, 100 + i)))
    lines += ["", "#### against the weaker's share (3 widths apart, 1 000 counts)", "", *HEAD]
    for est in ests:
        for i, share in enumerate((0.1, 0.2, 0.3, 0.4, 0.5)):
            lines.append(row(cell(est, 3.0, share, 1000.0, args.pixels, 200 + i)))
    lines += ["", "#### background only (p_fa 1e-3, 3 returns a pixel, 400 bins): pixels with "
              "any detected return", "", "| estimator | counts a bin | pixels | with a "
              "detection | share |", "|---|---|---|---|---|"]
    for est in ests:
        for b in (1e-3, 0.3, 30.0):
            rng = np.random.default_rng(int(b * 1e3) + 9)
            n = 2000
            c = rng.poisson(b, (n, 400)).astype(float)
            h = Histograms(c, np.tile(np.arange(401) * BIN, (n, 1)), np.full(n, 1e9),
                           np.ones_like(c, bool))
            r = estimate_returns(h, SIGMA, est, P_FA, 3)
            k = len(set(r.pixel[r.detected].tolist()))
            lines.append(f"| {est} | {b:g} | {n} | {k} | {k / n:.2%} |")
    if args.only is None:
        lines += ["", *real_pairs(tuple(ests))]
    emit(lines, args.out)


if __name__ == "__main__":
    main()
