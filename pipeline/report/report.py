"""Markdown reports: tables from Polars frames, summaries shared by benchmarks and flows,
and a report written atomically next to its plots."""

from __future__ import annotations

from pathlib import Path

import polars as pl

from pipeline.io.atomic import atomic_path


def markdown_table(df: pl.DataFrame, digits: int = 3) -> str:
    """A Polars frame as a Markdown table (floats to ``digits`` significant figures)."""
    out = ["| " + " | ".join(map(str, df.columns)) + " |", "|" + "---|" * len(df.columns)]
    for row in df.iter_rows():
        out.append("| " + " | ".join(f"{v:.{digits}g}" if isinstance(v, float) else str(v)
                                     for v in row) + " |")
    return "\n".join(out)


def speed_error_summary(df: pl.DataFrame) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """Of a speed-against-error grid: the cells that count (detection > 90 %, SBR >= 1),
    each estimator's medians over them, and the median RMSE/CRLB by M."""
    good = df.filter((pl.col("detected") > 0.9) & (pl.col("sbr") >= 1))
    summary = (good.group_by("estimator").agg(
        pl.col("hist_per_s").median().alias("median hist/s"),
        pl.col("rmse_over_crlb").median().alias("median RMSE/CRLB"),
        pl.col("rmse_over_crlb").quantile(0.9).alias("90th pct RMSE/CRLB"),
        pl.col("bias_ps").abs().median().alias("median |bias| ps"),
        pl.col("outliers_5crlb").mean().alias("outliers > 5 CRLB"),
        pl.col("coverage_2sigma").median().alias("2-sigma coverage"))
        .sort("median RMSE/CRLB"))
    by_m = (good.group_by("estimator", "m").agg(pl.col("rmse_over_crlb").median())
            .sort("m").pivot(on="m", index="estimator", values="rmse_over_crlb")
            .sort("estimator"))
    return good, summary, by_m


def write_report(path: str | Path, title: str, sections: list[tuple[str, str]]) -> Path:
    """A Markdown report: a title and (heading, body) sections, written atomically."""
    text = [f"# {title}", ""]
    for heading, body in sections:
        text += [f"## {heading}", "", body.rstrip(), ""]
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(text))
    return path
