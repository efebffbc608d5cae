"""Code-density calibration of a LinoSPAD2 capture against the board's published table.

The capture is a uniform-light (code-density) test of the FPGA's 64 carry-chain TDCs: each
fine code's share of the hits is its width (``stages.instruments.linospad2.CodeDensity``).
The published table (daplis' ``TDC_<db>_<mb>_<fw>.csv``) is the same measurement made by the
board's authors on another capture: per pixel, ``cumsum(counts) / total x 2500`` ps, i.e.
the time at each code's upper edge (the ``"upper"`` convention; :func:`convention_scan`
shows the data agree: it has the smallest RMS and a mean difference of ~0, where ``"centre"``
and ``"lower"`` are off by half and a whole mean width, ~9 and ~18 ps). Its widths are
multiples of 2500 ps / N for an integer N (~390 per pixel): so it is one capture of about
our size, with statistical errors of its own, and the expected disagreement is binomial
from both (``Comparison.expected_rms_ps``).

    compare_with_published(dat, csv, "2212b")   # -> pyarrow.Table, one row per pixel
    write_figure(dat, csv, "docs/img/linospad2_calibration.png")
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa

from pipeline.io import linospad2 as lio
from stages.instruments import linospad2 as lino

#: Monte Carlo draws of the statistics-only hypothesis (p-values to ~0.005; ~1.5 s)
N_NULL = 200


@dataclass(frozen=True)
class CalibrationComparison:
    """Everything one comparison computed: the measured density, the published table,
    the per-row comparison and the capture's tally."""

    by: str
    firmware: str
    measured: lino.CodeDensity
    published_ps: np.ndarray
    published_counts: np.ndarray
    comparison: lino.Comparison
    tally: lino.Tally


def calibrate(dat, firmware: str = "2212b", by: str = "pixel",
              words_per_line: int = lino.WORDS_PER_LINE) -> tuple[lino.CodeDensity, lino.Tally]:
    """Code-density calibration of a capture: (256 or 64, 140) code widths and times."""
    counts, tally = lio.histogram_file(dat, firmware, by=by, words_per_line=words_per_line)
    return lino.code_density(counts), tally


def _published_by(published_ps: np.ndarray, firmware: str, by: str):
    """The published table (and the counts behind it) per pixel, or pooled per TDC."""
    counts, n = lino.counts_from_cumulative(published_ps)
    if by == "pixel":
        return published_ps, np.where(n[:, None] > 0, counts, 0)
    if not np.all((n > 0) | (published_ps[:, -1] == 0)):
        raise lio.Linospad2Error("published rows are not single histograms: they cannot "
                                 "be pooled per TDC")
    pooled = lino.pool_by_tdc(np.where(n[:, None] > 0, counts, 0), firmware)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.nan_to_num(lino.code_density(pooled).upper_ps), pooled


def compare(dat, csv, firmware: str = "2212b", by: str = "pixel", convention: str = "upper",
            seed: int = 0, n_null: int = N_NULL,
            words_per_line: int = lino.WORDS_PER_LINE) -> CalibrationComparison:
    """Measure the capture's code density and compare it with the published table.

    ``by="tdc"`` pools the 4 pixels of each TDC on both sides (they share one carry chain:
    4x the hits, half the statistical error).
    """
    if by not in ("pixel", "tdc"):
        raise lio.Linospad2Error(f"by must be 'pixel' or 'tdc', found {by!r}")
    measured, tally = calibrate(dat, firmware, by, words_per_line)
    table_ps, pub_counts = _published_by(lio.read_published_calibration(csv), firmware, by)
    cmp = lino.compare_code_times(measured.counts, table_ps, convention,
                                  published_counts=pub_counts,
                                  rng=np.random.default_rng(seed), n_null=n_null)
    return CalibrationComparison(by, firmware, measured, table_ps, pub_counts, cmp, tally)


def comparison_table(result: CalibrationComparison) -> pa.Table:
    """One row per pixel (or TDC): hits, RMS/max/mean difference, the binomial
    expectation, their ratio, the Monte Carlo p-value and the dead codes."""
    c = result.comparison
    n = c.rms_ps.size
    key = np.arange(n)
    cols = {result.by: pa.array(key.astype(np.uint16))}
    if result.by == "pixel":
        cols["tdc"] = pa.array(lino.tdc_of(key, result.firmware))
    cols.update({
        "hits": pa.array(c.hits.astype(np.int64)),
        "published_hits": pa.array(c.published_hits.astype(np.int64)),
        "rms_ps": pa.array(c.rms_ps),
        "max_ps": pa.array(c.max_ps),
        "mean_ps": pa.array(c.mean_ps),
        "expected_rms_ps": pa.array(c.expected_rms_ps),
        "expected_rms_own_ps": pa.array(c.expected_rms_own_ps),
        "ratio": pa.array(c.ratio),
        "p_value": pa.array(c.p_value),
        "dead_codes": pa.array(c.dead_codes.astype(np.int16)),
        "published_dead_codes": pa.array(c.published_dead_codes.astype(np.int16)),
        "dead_in_both": pa.array(c.dead_in_both.astype(np.int16)),
    })
    return pa.table(cols)


def compare_with_published(dat, csv, firmware: str = "2212b", by: str = "pixel",
                           seed: int = 0, n_null: int = N_NULL,
                           words_per_line: int = lino.WORDS_PER_LINE) -> pa.Table:
    """Per pixel (or TDC): pixel, hits, rms_ps, max_ps, expected_rms_ps, dead_codes, ...
    (:func:`comparison_table`); rows without hits in either table hold NaN."""
    return comparison_table(compare(dat, csv, firmware, by, seed=seed, n_null=n_null,
                                    words_per_line=words_per_line))


def convention_scan(dat, csv, firmware: str = "2212b") -> pa.Table:
    """The measured code times in each convention against the published table: pooled
    RMS, mean difference and median per-pixel RMS. The published convention is the one
    with a mean difference of ~0 (and the smallest RMS)."""
    counts, _ = lio.histogram_file(dat, firmware, by="pixel")
    pub = lio.read_published_calibration(csv)
    rows = {"convention": [], "pooled_rms_ps": [], "mean_diff_ps": [],
            "median_pixel_rms_ps": []}
    for conv in lino.CONVENTIONS:
        c = lino.compare_code_times(counts, pub, conv)
        live = c.live
        rows["convention"].append(conv)
        rows["pooled_rms_ps"].append(float(np.sqrt(np.mean(c.rms_ps[live] ** 2))))
        rows["mean_diff_ps"].append(float(np.mean(c.mean_ps[live])))
        rows["median_pixel_rms_ps"].append(float(np.median(c.rms_ps[live])))
    return pa.table(rows)


def shared_chains(dat, csv, firmware: str = "2212b", seed: int = 0,
                  n_null: int = N_NULL) -> dict[str, lino.Comparison]:
    """Do the 4 pixels of a TDC share one chain? Each pixel against the other 3 of its
    TDC, in this capture and in the published table; and, as a control that the test can
    see a difference, each TDC against the next one (this capture, 4 pixels pooled)."""
    counts, _ = lio.histogram_file(dat, firmware, by="pixel")
    counts = counts.astype(np.int64)
    pub_counts, n = lino.counts_from_cumulative(lio.read_published_calibration(csv))
    pub_counts = np.where(n[:, None] > 0, pub_counts, 0)
    rng = np.random.default_rng(seed)
    tdc = lino.pool_by_tdc(counts, firmware)
    nxt = np.roll(tdc, -1, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        nxt_ps = np.nan_to_num(lino.code_density(nxt).upper_ps)
    return {
        "this capture: pixel vs the other 3 of its TDC":
            lino.pixels_against_their_tdc(counts, firmware, rng, n_null),
        "published: pixel vs the other 3 of its TDC":
            lino.pixels_against_their_tdc(pub_counts, firmware, rng, n_null),
        "control, this capture: TDC vs the next TDC":
            lino.compare_code_times(tdc, nxt_ps, published_counts=nxt, rng=rng,
                                    n_null=n_null),
    }


def comparison_summary(c: lino.Comparison) -> dict:
    """Median ratio (and the null's), share within 2x, p < 0.01 count, for any comparison."""
    live = c.live & (c.published_hits > 0)
    null = c.null_ratio[:, live]
    return {"live": int(live.sum()), "median_rms_ps": float(np.median(c.rms_ps[live])),
            "median_ratio": float(np.median(c.ratio[live])),
            "null_median_ratio": float(np.nanmedian(null)) if null.size else float("nan"),
            "within_2x": float(np.mean(c.ratio[live] < 2)),
            "p_below_0.01": int(np.sum(c.p_value[live] < 0.01))}


def summary(result: CalibrationComparison) -> dict:
    """The headline numbers of a comparison (live rows only)."""
    c = result.comparison
    live = c.live
    null = c.null_ratio[:, live]
    out = {
        "rows": int(live.size), "live": int(live.sum()),
        "empty": np.flatnonzero(c.hits == 0).tolist(),
        "published_empty": np.flatnonzero(result.published_ps[:, -1] == 0).tolist(),
        "median_hits": float(np.median(c.hits[live])),
        "median_published_hits": float(np.median(c.published_hits[live])),
        "median_rms_ps": float(np.median(c.rms_ps[live])),
        "p95_rms_ps": float(np.percentile(c.rms_ps[live], 95)),
        "median_max_ps": float(np.median(c.max_ps[live])),
        "median_expected_rms_ps": float(np.median(c.expected_rms_ps[live])),
        "median_expected_rms_own_ps": float(np.median(c.expected_rms_own_ps[live])),
        "median_ratio": float(np.median(c.ratio[live])),
        "p95_ratio": float(np.percentile(c.ratio[live], 95)),
        "within_2x": float(np.mean(c.ratio[live] < 2)),
        "mean_diff_ps": float(np.mean(c.mean_ps[live])),
        # rows are independent captures of independent chains: the standard error
        "mean_diff_se_ps": float(np.std(c.mean_ps[live], ddof=1) / np.sqrt(live.sum())),
        # a systematic RMS difference s would add s^2 to every row's mean square: the
        # measured excess over the binomial expectation, and its 2-sigma upper limit on s
        **_systematic(c.rms_ps[live] ** 2 - c.expected_rms_ps[live] ** 2),
        "median_dead_codes": float(np.median(c.dead_codes[live])),
        "median_published_dead_codes": float(np.median(c.published_dead_codes[live])),
        "median_dead_in_both": float(np.median(c.dead_in_both[live])),
    }
    if null.size:
        out.update({
            "null_median_ratio": float(np.nanmedian(null)),
            "null_p95_ratio": float(np.nanpercentile(null, 95)),
            "null_within_2x": float(np.mean(null[np.isfinite(null)] < 2)),
            "p_below_0.01": int(np.sum(c.p_value[live] < 0.01)),
            "expected_p_below_0.01": float(0.01 * live.sum()),
        })
    return out


def _systematic(excess_ps2: np.ndarray) -> dict:
    mean = float(np.mean(excess_ps2))
    se = float(np.std(excess_ps2, ddof=1) / np.sqrt(excess_ps2.size))
    return {"excess_ms_ps2": mean, "excess_ms_se_ps2": se,
            "systematic_limit_ps": float(np.sqrt(max(0.0, mean + 2 * se)))}


def write_figure(result: CalibrationComparison, out, pixel: int | None = None,
                 by_tdc: CalibrationComparison | None = None) -> Path:
    """The comparison as a figure (PNG, Agg): (a) one pixel's code times, measured and
    published; (b) their difference with the binomial +-1 sigma band; (c) per-pixel RMS
    difference against hits, with the expected-statistics curves; (d) the RMS over its
    expectation against the Monte Carlo distribution of pure statistics."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    c, m = result.comparison, result.measured
    live = c.live
    if pixel is None:  # the live pixel whose ratio is the median one: a typical pixel
        order = np.flatnonzero(live)[np.argsort(c.ratio[live])]
        pixel = int(order[order.size // 2])
    k = np.arange(lino.N_FINE)
    fig, ax = plt.subplots(2, 2, figsize=(11, 8.5))
    a = ax[0, 0]
    a.step(k, result.published_ps[pixel], where="mid", label="published (TDC_A5_#36_2212b)")
    a.step(k, m.upper_ps[pixel], where="mid", label="this capture (code density)")
    a.plot(k, (k + 1) * lino.CODE_PS, "k:", lw=0.8, label="ideal 17.857 ps codes")
    a.set(xlabel="fine code", ylabel="code time, upper edge (ps)",
          title=f"(a) pixel {pixel}: {c.hits[pixel]} hits here, "
                f"{c.published_hits[pixel]} published")
    a.legend(fontsize=8)
    a = ax[0, 1]
    pc = result.published_counts[pixel]
    f = np.cumsum(m.counts[pixel].astype(float) + pc) / (c.hits[pixel] + pc.sum())
    sig = np.sqrt(f * (1 - f) * (1 / c.hits[pixel] + 1 / max(pc.sum(), 1))) * lino.CLOCK_PS
    a.fill_between(k, -sig, sig, color="0.85", step="mid", label="binomial ±1σ (both)")
    a.step(k, m.upper_ps[pixel] - result.published_ps[pixel], where="mid", color="C3",
           label=f"measured - published: RMS {c.rms_ps[pixel]:.0f} ps")
    a.axhline(0, color="k", lw=0.5)
    a.set(xlabel="fine code", ylabel="difference (ps)", title="(b) the difference, same pixel")
    a.legend(fontsize=8)
    a = ax[1, 0]
    a.scatter(c.hits[live], c.rms_ps[live], s=8, label="pixels: RMS difference")
    hi = c.hits[live].max()
    if by_tdc is not None:
        t = by_tdc.comparison
        a.scatter(t.hits[t.live], t.rms_ps[t.live], s=10, marker="^", color="C4",
                  label="TDCs (4 pixels pooled, both tables)")
        hi = max(hi, t.hits[t.live].max())
    n = np.geomspace(max(c.hits[live].min() * 0.8, 1), hi * 1.2, 200)
    with np.errstate(invalid="ignore", divide="ignore"):
        # the median over pixels of mean_k F (1 - F), and of N_pub / N
        fbar = np.nanmedian((c.expected_rms_own_ps[live] / lino.CLOCK_PS) ** 2
                            * c.hits[live])
        rho = np.median(c.published_hits[live] / c.hits[live])
    own = np.sqrt(fbar / n) * lino.CLOCK_PS
    both = np.sqrt(fbar * (1 / n + 1 / (rho * n))) * lino.CLOCK_PS
    a.plot(n, own, "C1--", label="expected, this capture only: sqrt(F(1-F)/N)·2500")
    a.plot(n, both, "C2-", label=f"expected, both tables (N_pub = {rho:.2f} N)")
    a.plot(n, 2 * both, "C2:", label="2x that")
    a.set(xscale="log", yscale="log", xlabel="hits in this capture (N)",
          ylabel="RMS difference (ps)", title="(c) RMS difference against hits")
    a.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ticks = [x for x in (100, 200, 500, 1000, 2000, 5000, 10000) if n[0] <= x <= n[-1]]
    a.set_xticks(ticks, labels=[str(x) for x in ticks])
    a.legend(fontsize=7)
    a = ax[1, 1]
    bins = np.linspace(0, 3, 31)
    null = c.null_ratio[:, live]
    if null.size:
        a.hist(null[np.isfinite(null)], bins=bins, density=True, histtype="step", color="k",
               label="pure statistics (Monte Carlo)")
    a.hist(c.ratio[live], bins=bins, density=True, alpha=0.6,
           label=f"pixels (median {np.median(c.ratio[live]):.2f})")
    a.set(xlabel="RMS difference / binomial expectation", ylabel="density",
          title="(d) is the disagreement statistics?")
    a.legend(fontsize=8)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
