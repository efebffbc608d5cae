"""LinoSPAD2: code-density calibration of the real board against its published table.

Reads the sample capture (firmware 2212b, uniform light) and the board's published TDC
calibration, compares them per pixel and per TDC (the 4 pixels of a TDC pooled), and writes
the Markdown summary (``benchmarks/results/linospad2_calibration.md``) and the figure
(``docs/img/linospad2_calibration.png``). No arguments: the paths are the shared data's.

    python benchmarks/linospad2_calibration.py
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.datapath import emit, machine  # noqa: E402
from pipeline.offline import linospad2_cal as cal  # noqa: E402

DATA = ROOT / "tests" / "data" / "linospad2"  # the public files of tests/data/README.md
DAT = DATA / "test_data_2212b.dat"
CSV = DATA / "TDC_A5_#36_2212b.csv"
FIRMWARE = "2212b"
OUT = ROOT / "benchmarks" / "results" / "linospad2_calibration.md"
FIGURE = ROOT / "docs" / "img" / "linospad2_calibration.png"


def main() -> None:
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    by_pixel = cal.compare(DAT, CSV, FIRMWARE, by="pixel", seed=0)
    by_tdc = cal.compare(DAT, CSV, FIRMWARE, by="tdc", seed=1)
    scan = cal.convention_scan(DAT, CSV, FIRMWARE).to_pylist()
    shared = {k: cal.comparison_summary(v)
              for k, v in cal.shared_chains(DAT, CSV, FIRMWARE, seed=2).items()}
    cal.write_figure(by_pixel, FIGURE, by_tdc=by_tdc)
    elapsed = time.perf_counter() - t0
    p, t = cal.summary(by_pixel), cal.summary(by_tdc)
    tally = by_pixel.tally
    lines = [
        "# LinoSPAD2 code-density calibration against the published table",
        "",
        f"`{' '.join(['python', 'benchmarks/linospad2_calibration.py'])}` on {machine()}; "
        f"{elapsed:.1f} s (with the figure and {cal.N_NULL} Monte Carlo draws per table; "
        f"1-minute load average {load:.1f} at the start, other work shared the cores).",
        "",
        f"Capture `{DAT.name}` ({DAT.stat().st_size} bytes, firmware {FIRMWARE}): "
        f"{tally.cycles} cycles, {tally.words} words = {tally.valid} photon words + "
        f"{tally.invalid} padding + {tally.line65} in the 65th line "
        f"({tally.line65_valid} of them valid), {tally.truncated_bytes} bytes truncated. "
        f"Published table `{CSV.name}`.",
        "",
        "| | per pixel | per TDC (4 pixels pooled) |",
        "|---|---|---|",
        f"| rows compared (hits in both) | {p['live']} of {p['rows']} | "
        f"{t['live']} of {t['rows']} |",
        f"| median hits: this capture / published | {p['median_hits']:.0f} / "
        f"{p['median_published_hits']:.0f} | {t['median_hits']:.0f} / "
        f"{t['median_published_hits']:.0f} |",
        f"| median RMS difference (ps) | {p['median_rms_ps']:.1f} | {t['median_rms_ps']:.1f} |",
        f"| 95th percentile RMS difference (ps) | {p['p95_rms_ps']:.1f} | "
        f"{t['p95_rms_ps']:.1f} |",
        f"| median max difference (ps) | {p['median_max_ps']:.1f} | {t['median_max_ps']:.1f} |",
        f"| median expected RMS, both tables' statistics (ps) | "
        f"{p['median_expected_rms_ps']:.1f} | {t['median_expected_rms_ps']:.1f} |",
        f"| median expected RMS, this capture's only (ps) | "
        f"{p['median_expected_rms_own_ps']:.1f} | {t['median_expected_rms_own_ps']:.1f} |",
        f"| RMS / expected: median (pure statistics: Monte Carlo) | "
        f"{p['median_ratio']:.2f} ({p['null_median_ratio']:.2f}) | "
        f"{t['median_ratio']:.2f} ({t['null_median_ratio']:.2f}) |",
        f"| RMS / expected: 95th percentile (Monte Carlo) | {p['p95_ratio']:.2f} "
        f"({p['null_p95_ratio']:.2f}) | {t['p95_ratio']:.2f} ({t['null_p95_ratio']:.2f}) |",
        f"| within 2x the expectation (Monte Carlo) | {100 * p['within_2x']:.1f} % "
        f"({100 * p['null_within_2x']:.1f} %) | {100 * t['within_2x']:.1f} % "
        f"({100 * t['null_within_2x']:.1f} %) |",
        f"| p < 0.01 (expected by chance) | {p['p_below_0.01']} "
        f"({p['expected_p_below_0.01']:.1f}) | {t['p_below_0.01']} "
        f"({t['expected_p_below_0.01']:.1f}) |",
        f"| mean difference, measured - published (ps) | {p['mean_diff_ps']:+.1f} ± "
        f"{p['mean_diff_se_ps']:.1f} | {t['mean_diff_ps']:+.1f} ± {t['mean_diff_se_ps']:.1f} |",
        f"| excess mean square over the expectation (ps²) | {p['excess_ms_ps2']:+.0f} ± "
        f"{p['excess_ms_se_ps2']:.0f} | {t['excess_ms_ps2']:+.0f} ± {t['excess_ms_se_ps2']:.0f} |",
        f"| systematic RMS difference, 2σ upper limit (ps) | "
        f"{p['systematic_limit_ps']:.1f} | {t['systematic_limit_ps']:.1f} |",
        f"| median dead codes: this capture / published / both | "
        f"{p['median_dead_codes']:.0f} / {p['median_published_dead_codes']:.0f} / "
        f"{p['median_dead_in_both']:.0f} | {t['median_dead_codes']:.0f} / "
        f"{t['median_published_dead_codes']:.0f} / {t['median_dead_in_both']:.0f} |",
        "",
        f"Pixels without hits here: {p['empty']}; empty in the published table: "
        f"{p['published_empty']}.",
        "",
        "The published table's convention (measured code times in each convention against it):",
        "",
        "| convention | pooled RMS (ps) | mean difference (ps) | median pixel RMS (ps) |",
        "|---|---|---|---|",
        *[f"| {r['convention']} | {r['pooled_rms_ps']:.1f} | {r['mean_diff_ps']:+.1f} | "
          f"{r['median_pixel_rms_ps']:.1f} |" for r in scan],
        "",
        "Do the 4 pixels of a TDC share one carry chain? (RMS / binomial expectation; the "
        "Monte Carlo null's median in brackets)",
        "",
        "| comparison | rows | median RMS (ps) | median ratio (null) | within 2x | p < 0.01 |",
        "|---|---|---|---|---|---|",
        *[f"| {k} | {v['live']} | {v['median_rms_ps']:.1f} | {v['median_ratio']:.2f} "
          f"({v['null_median_ratio']:.2f}) | {100 * v['within_2x']:.1f} % | "
          f"{v['p_below_0.01']} |" for k, v in shared.items()],
        "",
        f"Figure: `{FIGURE.relative_to(ROOT)}`.",
    ]
    emit(lines, OUT)


if __name__ == "__main__":
    main()
