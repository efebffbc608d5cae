"""``tcspc demo`` (what ``make demo`` runs): the whole story on embedded defaults, outputs
under ``./data``.

1. the data path checked exactly on a synthetic capture, and the street scene's peaks
   where their distances put them (``pipeline.report.demo``);
2. a calibration campaign on the simulated chip (Prefect flow, embedded ephemeral API):
   density tests at five light levels, the LSB polynomial, the zero-distance delay, a
   report with plots; published to ``data/calibration/current`` unless worse;
3. the street scene through the streaming daemon (simulator -> two histogram workers by TDC
   range -> range -> parquet sink), with its accounting;
4. a table of ranges against truth, and the paths of the reports and plots.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import click
import polars as pl
from rich.console import Console
from rich.table import Table

ROOT = Path(__file__).resolve().parents[1]


def street_truth() -> list[tuple[str, int, int, float]]:
    from stages.models.scene import load_scene

    names = {9.0: "car", 6.5: "pedestrian", 14.0: "wall"}
    return [(names.get(t.distance_m, "target"), t.pixels[0], t.pixels[1], t.distance_m)
            for t in load_scene(ROOT / "scenes" / "street.toml").targets]


def run_story(out: str | Path = "data", cycles: int = 100_000,
              calibration_cycles: int = 400_000, inl_rms: float = 0.5,
              console: Console | None = None) -> dict:
    from flows.calibration import calibration_campaign
    from pipeline.report.demo import run_demo
    from pipeline.stream.daemon import Supervisor
    from pipeline.stream.topology import load_topology

    con = console or Console(stderr=True, markup=False)  # paths are printed as they are
    out = Path(out)
    checks = run_demo(out, cycles, console=con)

    con.rule("6. calibration campaign on the simulated chip (Prefect flow)")
    cal = calibration_campaign(out=str(out / "calibration"), cycles=calibration_cycles,
                               inl_rms=inl_rms)
    con.print(f"published: {cal['published']}; report {cal['report']}")
    current = out / "calibration" / "current"

    con.rule("7. the street scene through the streaming daemon")
    # a fresh run: the daemon resumes a run id it has journaled (what a daemon should do),
    # which would replay a previous demo's datasets against this calibration
    for d in (out / "daemon", out / "stream"):
        shutil.rmtree(d, ignore_errors=True)
    topo = load_topology(None, "street", overrides={
        "daemon": {"state": str(out / "daemon")},
        "source": {"cycles": cycles},
        "histogram": {"calibration": str(current)},
        "range": {"calibration": str(current)},
        "sink": {"out": str(out / "stream")}})
    res = Supervisor(topo, log=lambda m: con.print(f"daemon: {m}", highlight=False)).run()
    if res["failed"]:
        raise click.ClickException(f"daemon: {res['failed']}")
    acc = res["accounting"]
    con.print(f"accounting: {acc['words_in']:,} words in, classified {acc['classified']:,} "
              f"({acc['classes']}); balanced: {acc['balanced']}")

    con.rule("8. ranges against truth (Polars over the ranges dataset)")
    ranges = pl.read_parquet(out / "stream" / "ranges" / "date=*" / "run=street" / "*.parquet",
                             hive_partitioning=True)
    table = Table(title="street scene: ranges against truth (median over pixels and "
                        "measurements of detected pixels)")
    for col in ("target", "pixels", "truth m", "measured m", "error cm", "sigma cm",
                "detected"):
        table.add_column(col)
    rows = []
    for name, lo, hi, d in street_truth():
        r = ranges.filter(pl.col("tdc").is_between(lo, hi))
        det = r.filter(pl.col("detected"))
        med = float(det["distance_m"].median()) if det.height else float("nan")
        rows.append({"target": name, "truth_m": d, "measured_m": med,
                     "error_cm": (med - d) * 100, "detected": float(r["detected"].mean())})
        table.add_row(name, f"{lo}-{hi}", f"{d:.2f}", f"{med:.3f}", f"{(med - d) * 100:+.1f}",
                      f"{float(det['sigma_m'].median()) * 100:.2f}" if det.height else "-",
                      f"{r['detected'].mean():.0%}")
    Console().print(table)
    figure = _street_figure(out, ranges)
    ok = checks["exact"] and checks["street_ok"] and acc["balanced"] and all(
        abs(r["error_cm"]) < 5 and r["detected"] > 0.5 for r in rows)
    paths = {"calibration report": cal["report"], "calibration plots": cal["plots"],
             "street figure": str(figure),
             "ranges dataset": str(out / "stream" / "ranges"),
             "histograms dataset": str(out / "stream" / "histograms"),
             "accounting": acc["path"], "daemon status": str(out / "daemon" / "status.json")}
    for k, v in paths.items():
        con.print(f"{k}: {v}")
    con.print(f"every check passed: {ok}")
    con.print(f"look at it live: tcspc view --state {out / 'daemon'} --out {out / 'stream'} "
              f"--calibration {out / 'calibration' / 'current'}  (then open the URL it prints, "
              "with its token: http://127.0.0.1:5006/?token=...)", highlight=False, soft_wrap=True)
    summary = {**checks, "calibration": cal["current"], "ranges": rows, "ok": ok, **paths}
    (out / "demo.json").write_text(json.dumps(summary, indent=1, default=str))
    return summary


def _street_figure(out: Path, ranges: pl.DataFrame) -> Path:
    """The picture of what the daemon found: ranges per pixel, one car pixel's histogram."""
    from pipeline.report.figures import street_figure

    per_pixel = (ranges.filter(pl.col("detected")).group_by("tdc")
                 .agg(pl.col("distance_m").median()).sort("tdc"))
    truth = street_truth()
    car = next((lo for name, lo, _, _ in truth if name == "car"), truth[0][1])
    hist = pl.read_parquet(out / "stream" / "histograms" / "date=*" / "run=street" / "*.parquet",
                           hive_partitioning=True).filter(pl.col("tdc") == car).sort("measurement")
    counts = hist["counts"].to_list()[0] if hist.height else [0] * 512
    return street_figure(per_pixel["tdc"].to_numpy(), per_pixel["distance_m"].to_numpy(),
                         [True] * per_pixel.height, truth, car, counts, out / "street.png")


@click.command()
@click.option("--out", default="data", show_default=True, type=click.Path())
@click.option("--cycles", default=100_000, show_default=True, type=click.IntRange(1))
def demo(out, cycles) -> None:
    """The whole story on embedded defaults (what `make demo` runs)."""
    result = run_story(out, cycles)
    if not result["ok"]:
        from pipeline.cli.console import Incomplete

        raise Incomplete("demo: a check failed (see above; every check and its result: "
                         f"{out}/demo.json)")



