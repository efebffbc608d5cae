"""The ``tcspc`` command line (DESIGN.md "Command line")."""

from __future__ import annotations

import json
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import click
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    ProgressColumn,
    TextColumn,
    TimeRemainingColumn,
)
from rich.table import Table

# Heavy modules (numpy, pyarrow, numba, scipy) are imported in the commands that use them:
# `tcspc --help` and a command's own --help stay fast (tests/pipeline/cli/test_cli.py checks).

err = Console(stderr=True)
out = Console()


class _RateColumn(ProgressColumn):
    """Items per second, in millions."""

    def render(self, task):
        speed = task.finished_speed or task.speed
        return TextColumn("").render(task) if speed is None else f"{speed / 1e6:.1f} M/s"


@contextmanager
def _progress(total: int, passes: int, quiet: bool, label: str, unit: str = "words"):
    """A progress bar over ``total`` items (words or cycles), all passes, on stderr."""
    if quiet:
        yield lambda n: None
        return
    cols = [TextColumn(f"[bold]{label}"), BarColumn(), MofNCompleteColumn(),
            TextColumn(unit), _RateColumn(), TimeRemainingColumn()]
    with Progress(*cols, console=err, transient=False) as bar:
        task = bar.add_task(label, total=total * passes)
        yield lambda n: bar.advance(task, n)


def _summary(counts, n_words: int, seconds: float, bounds_source: str,
             verb: str = "read") -> None:
    from schemas import WORD_CLASSES

    total = int(sum(counts))
    table = Table(title="word classes", show_footer=True)
    table.add_column("class", footer="total")
    table.add_column("words", justify="right", footer=f"{total:,}")
    table.add_column("share", justify="right", footer="100%" if total else "-")
    for name, c in zip(WORD_CLASSES, counts, strict=True):
        table.add_row(name, f"{int(c):,}", f"{100 * int(c) / total:.4g}%" if total else "-")
    err.print(table)
    err.print(f"{n_words:,} words {verb} in {seconds:.2f} s "
              f"({n_words / max(seconds, 1e-9) / 1e6:.1f} M words/s); "
              f"artifact bounds: {bounds_source}")
    if total != n_words:  # every word is accounted for, or this is a bug worth stopping on
        raise click.ClickException(f"accounting error: classes add up to {total}, "
                                   f"{n_words} words were read")


def _warn_uncertain(bounds) -> None:
    """Estimated bounds the data cannot vouch for are said, even with --quiet."""
    if bounds.uncertain.any():
        err.print(f"[yellow]warning:[/yellow] artifact bounds uncertain on "
                  f"{int(bounds.uncertain.sum())} TDC(s): {bounds.describe()}; give "
                  "--calibration for exact bounds", highlight=False)


def _open(path: str, calibration: str | None):
    from pipeline.io.caldir import read_bounds
    from pipeline.io.capture import Capture

    cap = Capture(path)
    bounds = read_bounds(calibration, cap.meta.n_tdc) if calibration else None
    return cap, bounds


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="tcspc-lidar")
def cli() -> None:
    """tcspc-lidar: raw SPAD/TDC words to calibrated distances."""


_calibration = click.option("--calibration", "calibration", type=click.Path(exists=True),
                            help="Calibration directory (Nmin/Nmax per TDC). Without it the "
                                 "artifact bounds are estimated from the capture itself.")
_engine = click.option("--engine", type=click.Choice(["numba", "numpy"]), default=None,
                       help="Hot-path engine (default: numba where installed).")
_quiet = click.option("-q", "--quiet", is_flag=True, help="No progress bar or summary.")


@cli.command()
@click.argument("capture", type=click.Path())
@click.option("--out", required=True, type=click.Path(), help="events.parquet to write")
@click.option("--include-no-hit", is_flag=True,
              help="Also write no_hit words as rows (they are always counted).")
@_calibration
@_engine
@_quiet
def decode(capture, out, include_no_hit, calibration, engine, quiet) -> None:
    """Decode CAPTURE (NAME.bin) into a decoded_events parquet file."""
    from pipeline.offline.datapath import decode_capture

    cap, bounds = _open(capture, calibration)
    t0 = time.perf_counter()
    with _progress(cap.n_words, 1 + (bounds is None), quiet, "decode") as step:
        counts, bounds = decode_capture(cap, out, bounds, include_no_hit, engine, step)
    if not quiet:
        _summary(counts, cap.n_words, time.perf_counter() - t0, bounds.describe())
        err.print(f"wrote {out}")
    _warn_uncertain(bounds)


@cli.command()
@click.argument("capture", type=click.Path())
@click.option("--out", required=True, type=click.Path(), help="hist.parquet to write")
@click.option("--measurement", default=None, help="Measurement name (default: capture name)")
@_calibration
@_engine
@_quiet
def histogram(capture, out, measurement, calibration, engine, quiet) -> None:
    """Per-TDC histograms of first-stage codes of CAPTURE's hit words."""
    from pipeline.offline.datapath import histogram_capture, write_histograms

    cap, bounds = _open(capture, calibration)
    t0 = time.perf_counter()
    with _progress(cap.n_words, 1, quiet, "histogram") as step:
        state, bounds = histogram_capture(cap, bounds, engine, step,
                                          log=lambda m: err.print(f"histogram: {m}"))
    write_histograms(state, measurement or cap.name, out,
                     {"capture": cap.bin_path, "bounds": bounds.describe()})
    if not quiet:
        _summary(state.class_counts.sum(axis=1), cap.n_words, time.perf_counter() - t0,
                 bounds.describe())
        err.print(f"wrote {out}")
    _warn_uncertain(bounds)


@cli.command()
@click.argument("out", type=click.Path())
@click.option("--cycles", default=40_000, show_default=True, type=click.IntRange(1))
@click.option("--n-tdc", default=128, show_default=True, type=click.IntRange(1, 256))
@click.option("--hit-prob", default=0.05, show_default=True, type=click.FloatRange(0, 1))
@click.option("--peak-code", default=300.0, show_default=True)
@click.option("--seed", default=0, show_default=True)
def pattern(out, cycles, n_tdc, hit_prob, peak_code, seed) -> None:
    """Write a synthetic capture OUT(.bin) with a known class mix (not the simulator).

    Its sidecar's truth holds the intended class counts, so decode and histogram can be
    checked against it.
    """
    from pipeline.io.capture import CaptureWriter
    from schemas import WORD_CLASSES
    from stages.testpattern import pattern_words

    words, truth = pattern_words(cycles, n_tdc, hit_prob=hit_prob, peak_code=peak_code,
                                 rng=seed)
    with CaptureWriter(out, n_tdc, kind="pattern", note=f"pattern_words seed={seed}") as w:
        w.write(words)
        w.set_truth({"generator": "stages.testpattern.pattern_words",
                     "class_counts": dict(zip(WORD_CLASSES,
                                              truth.class_counts.sum(axis=1).tolist(),
                                              strict=True)),
                     "n_min": truth.n_min.tolist(), "n_max": truth.n_max.tolist()})
    err.print(f"wrote {w.bin_path} ({words.size:,} words, {cycles:,} cycles)")


@cli.command()
@click.option("--markdown", is_flag=True, help="Markdown tables (as in docs/schemas.md).")
def schema(markdown) -> None:
    """Print every Arrow schema of the project with its version and units."""
    from schemas import ALL_SPECS, docs_markdown

    if markdown:
        click.echo(docs_markdown(), nl=False)
        return
    for spec in ALL_SPECS:
        out.print(f"[bold]{spec.name}[/bold] {spec.version}")
        out.print(str(spec.schema), markup=False, highlight=False)


@cli.command()
@click.argument("scene_path", type=click.Path(exists=True, dir_okay=False))
@click.option("--cycles", default=40_000, show_default=True, type=click.IntRange(1))
@click.option("--out", required=True, type=click.Path(), help="NAME.bin to write")
@click.option("--seed", default=0, show_default=True, help="Seed of the photons.")
@click.option("--chip-seed", default=1, show_default=True, help="Seed of the chip's "
              "LSB, INL and second-stage parameters (the same chip across captures).")
@click.option("--engine", type=click.Choice(["fast", "reference"]), default=None,
              help="Default: fast, or reference when a target moves.")
@click.option("--malformed-rate", default=0.0, show_default=True,
              type=click.FloatRange(0, 1), help="Fraction of words to corrupt (markers).")
@click.option("--invalid-rate", default=0.0, show_default=True,
              type=click.FloatRange(0, 1), help="Fraction of words given a bubble code.")
@click.option("--ideal-tdc", is_flag=True, help="No INL/DNL and no artifact.")
@_quiet
def simulate(scene_path, cycles, out, seed, chip_seed, engine, malformed_rate, invalid_rate,
             ideal_tdc, quiet) -> None:
    """Simulate SCENE_PATH: a raw capture whose sidecar holds the truth."""
    from pipeline.offline.simulate import simulate_capture

    t0 = time.perf_counter()
    with _progress(cycles, 1, quiet, "simulate", "cycles") as step:
        meta, sim = simulate_capture(scene_path, cycles, out, seed=seed, chip_seed=chip_seed,
                                     engine=engine, malformed_rate=malformed_rate,
                                     invalid_rate=invalid_rate, ideal_tdc=ideal_tdc,
                                     progress=step)
    if not quiet:
        dt = time.perf_counter() - t0
        err.print(f"wrote {out}: {cycles:,} cycles x {meta.n_tdc} TDCs, {sim.engine_name} "
                  f"engine, {dt:.2f} s ({cycles * meta.n_tdc / dt / 1e6:.1f} M TDC-cycles/s)")
        _summary(sim.result.class_counts.sum(axis=1), cycles * meta.n_tdc, dt,
                 "(the simulator's truth)", verb="written")
        for e in sim.sm.report:
            err.print(f"  {e.name}: {e.status} ({e.detail}: {e.size:.3g})", highlight=False)


@cli.command("range", short_help="Distance per pixel (eq. 5.4) from a capture and a calibration.")
@click.argument("capture", type=click.Path())
@click.option("--calibration", required=True, type=click.Path(exists=True, file_okay=False))
@click.option("--out", required=True, type=click.Path(), help="ranges.parquet to write")
@click.option("--estimator", type=click.Choice(["ml", "fast", "matched", "centroid", "gaussfit"]),
              default="ml", show_default=True)
@click.option("--irf-ps", type=float, default=None,
              help="Instrument response sigma (default: measured with the delay, else 1 LSB).")
@click.option("--p-fa", default=1e-3, show_default=True, help="False-alarm probability.")
@_quiet
def range_cmd(capture, calibration, out, estimator, irf_ps, p_fa, quiet) -> None:
    """Distance per pixel (eq. 5.4) with uncertainty and a detection decision."""
    from pipeline.io.caldir import load_calibration
    from pipeline.offline.ranging import range_capture

    t0 = time.perf_counter()
    calib = load_calibration(calibration)
    table, note = range_capture(capture, calib, out, estimator,
                                None if irf_ps is None else irf_ps * 1e-12, p_fa)
    if note:
        err.print(f"[yellow]warning:[/yellow] {note}", highlight=False)
    if not quiet:
        import polars as pl

        df = pl.from_arrow(table)
        det = df.filter(pl.col("detected"))
        err.print(f"{det.height} of {df.height} pixels detected ({estimator}, P_fa {p_fa:g}) in "
                  f"{time.perf_counter() - t0:.2f} s; distance "
                  f"{det['distance_m'].min() if det.height else float('nan'):.3f}.."
                  f"{det['distance_m'].max() if det.height else float('nan'):.3f} m, median "
                  f"sigma {det['sigma_m'].median() if det.height else float('nan'):.4f} m")
        err.print(f"wrote {out}")
    _warn_no_delay(calib)


def _warn_no_delay(calib) -> None:
    """TDCs the calibration has no delay for are not ranged: say how many and why."""
    from collections import Counter

    why = Counter(r for r in calib.delay_reasons if r)
    if why:
        err.print(f"[yellow]warning:[/yellow] {sum(why.values())} TDC(s) not ranged, no delay "
                  "in the calibration: " + "; ".join(f"{n} {r}" for r, n in why.most_common()),
                  highlight=False)


@cli.group()
def stage() -> None:
    """Run one stage of the stream alone (the graph can span processes and hosts)."""


_push = click.option("--push", "pushes", required=True, multiple=True,
                     help="Endpoint to send to, e.g. ipc:///tmp/h; one per worker with --split.")
_split = click.option("--split", default=None,
                      help="Fan out by TDC range, one range per --push: 0:64,64:128.")
_metrics = click.option("--metrics", default=None,
                        help="Endpoint to publish heartbeats and counters on (PUB).")
_date = click.option("--date", default=None, help="The run's date partition (default: today).")
_accept = click.option("--accept", "senders", multiple=True,
                       help="Step id this stage takes messages from (repeat; default: any).")
_journal_compression = click.option(
    "--journal-compression", type=click.Choice(["zstd", "none"]), default="zstd",
    show_default=True, help="Journal segments as zstd frames (RUN-N.bin.zst; `zstd -d` gives "
                            "the raw capture) or raw (RUN-N.bin).")


def _compression(name: str) -> str | None:
    return None if name == "none" else name


def _ranges(split: str | None):
    from pipeline.stream.fanout import parse_range

    return None if split is None else [parse_range(x) for x in split.split(",")]


def _skip_journaled(batches, journal, run_id):
    """A restarted source resumes after what its journal already holds (deterministic
    sources only: the simulator and capture replay)."""
    from pipeline.stream.journal import journaled_words

    done = journaled_words(journal, run_id) if journal else 0
    for first, words in batches:
        if first + words.size <= done:
            continue
        yield first, words


@stage.command("source-sim")
@click.argument("scene_path", type=click.Path(exists=True, dir_okay=False))
@click.option("--cycles", default=40_000, show_default=True, type=click.IntRange(1))
@_push
@click.option("--seed", default=0, show_default=True)
@click.option("--chip-seed", default=1, show_default=True)
@click.option("--run", "run_id", default="sim", show_default=True)
@click.option("--rate", type=float, default=None, help="Words per second (default: max).")
@click.option("--journal", type=click.Path(), default=None,
              help="Journal the words here before sending them.")
@_journal_compression
@_split
@_metrics
@_date
def stage_source_sim(scene_path, cycles, pushes, seed, chip_seed, run_id, rate, journal,
                     journal_compression, split, metrics, date) -> None:
    """The simulator as a source: raw-word batches of SCENE_PATH."""
    from pipeline.offline.simulate import make_simulator
    from pipeline.stream.journal import JournalWriter
    from pipeline.stream.stage import run_source

    sim = make_simulator(scene_path, cycles, seed=seed, chip_seed=chip_seed)
    n = sim.n_tdc
    gate = sim.sm.scene.gate.t_laser_win_ns
    batches = _skip_journaled(((first * n, w) for first, w in sim.batches(cycles)), journal,
                              run_id)
    jw = JournalWriter(journal, run_id, n, gate, sim.sm.scene.sensor.window_ns,
                       compression=_compression(journal_compression)) if journal else None
    sent = run_source(batches, list(pushes), step_id="source", run=run_id, n_tdc=n,
                      t_laser_win_ns=gate, rate_words_s=rate, journal=jw, split=_ranges(split),
                      metrics=metrics, window_ns=sim.sm.scene.sensor.window_ns, date=date)
    err.print(f"source-sim: sent {sent:,} words")


@stage.command("source-capture")
@click.argument("capture", type=click.Path())
@_push
@click.option("--run", "run_id", default=None, help="Run id (default: the capture's name)")
@click.option("--rate", type=float, default=None, help="Words per second (default: max).")
@click.option("--journal", type=click.Path(), default=None,
              help="Journal the words here before sending them.")
@_journal_compression
@_split
@_metrics
@_date
@click.option("--repeat", default=1, show_default=True, type=click.IntRange(1),
              help="Replay the capture this many times as one run (soak tests).")
def stage_source_capture(capture, pushes, run_id, rate, journal, journal_compression, split,
                         metrics, date, repeat) -> None:
    """Replay a capture into the stream, at a chosen rate or as fast as it is taken."""
    from pipeline.io.capture import Capture
    from pipeline.stream.journal import JournalWriter
    from pipeline.stream.stage import run_source

    cap = Capture(capture)
    run_id = run_id or cap.name
    n = cap.meta.n_tdc

    def replay():
        for k in range(repeat):
            for first, w in cap.iter_chunks(max(1, (1 << 18) // n) * n):
                # the chunk's buffer is reused: run_source journals and sends (copying)
                # each batch before it asks for the next
                yield k * cap.n_words + first, w

    batches = _skip_journaled(replay(), journal, run_id)
    jw = (JournalWriter(journal, run_id, n, cap.meta.t_laser_win_ns, cap.meta.window_ns,
                        compression=_compression(journal_compression)) if journal else None)
    sent = run_source(batches, list(pushes), step_id="source", run=run_id,
                      n_tdc=n, t_laser_win_ns=cap.meta.t_laser_win_ns,
                      rate_words_s=rate, journal=jw, split=_ranges(split), metrics=metrics,
                      window_ns=cap.meta.window_ns, date=date)
    err.print(f"source-capture: sent {sent:,} words")


@stage.command("ingest-udp")
@click.option("--bind", "bind_addr", default="127.0.0.1:9000", show_default=True,
              help="host:port to listen on (127.0.0.1 unless you choose otherwise)")
@_push
@click.option("--run", "run_id", default="udp", show_default=True)
@click.option("--journal", type=click.Path(), default=None,
              help="Directory for the raw words as capture segments (written before "
                   "they are passed on).")
@click.option("--quarantine", type=click.Path(), default=None)
@click.option("--idle", type=float, default=None, help="Stop after this many idle seconds.")
@click.option("--n-tdc", type=click.IntRange(1, 65535), default=None,
              help="The chip's TDCs per cycle (default: the first datagram's).")
@click.option("--reorder-window", type=click.IntRange(1), default=None,
              help="Datagrams held to undo UDP reordering (default 64).")
@click.option("--max-jump-cycles", type=click.IntRange(1), default=None,
              help="A datagram further past the newest cycle is refused (default 2^20).")
@_journal_compression
@_split
@_metrics
@_date
def stage_ingest_udp(bind_addr, pushes, run_id, journal, quarantine, idle, n_tdc,
                     reorder_window, max_jump_cycles, journal_compression, split, metrics,
                     date) -> None:
    """The FPGA's UDP datagrams (docs/streaming.md) in, journaled raw-word batches out."""
    import signal
    import threading

    from pipeline.stream.udp import MAX_JUMP_CYCLES, REORDER_WINDOW, run_udp_ingest, udp_socket

    halt = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: halt.set())
    stats = run_udp_ingest(udp_socket(bind_addr), list(pushes), run=run_id, journal=journal,
                           quarantine=quarantine, idle_s=idle, split=_ranges(split),
                           metrics=metrics, date=date, stop=halt,
                           compression=_compression(journal_compression), n_tdc=n_tdc,
                           reorder_window=reorder_window or REORDER_WINDOW,
                           max_jump_cycles=max_jump_cycles or MAX_JUMP_CYCLES)
    err.print(f"ingest: {stats.datagrams} datagrams, {stats.words:,} words, "
              f"{stats.lost_datagrams} lost, {stats.duplicates} duplicates, {stats.late} "
              f"late, {stats.gap_cycles} cycles in gaps, rejected {dict(stats.rejected)}")


@stage.command("histogram")
@click.option("--pull", required=True, help="Endpoint to bind for input")
@click.option("--push", required=True, help="Endpoint to send to")
@click.option("--n-tdc", default=128, show_default=True, help="TDCs per cycle (the chip's).")
@click.option("--tdc-range", default=None, help="This worker's TDCs, FIRST:END (a fan-out).")
@click.option("--measurement-cycles", type=click.IntRange(1), default=None,
              help="Emit a histogram per this many cycles (default: one at the run's end).")
@_calibration
@click.option("--quarantine", type=click.Path(), default=None)
@click.option("--checkpoint", type=click.Path(), default=None,
              help="Checkpoint file: restored at start, saved after every batch.")
@click.option("--journal", type=click.Path(), default=None,
              help="The source's journal directory, to fill gaps after a restart.")
@click.option("--run", "run_id", default=None, help="Run id of the journal to read.")
@_metrics
@click.option("--name", default="histogram", show_default=True, help="Name in metrics.")
@_date
@_accept
def stage_histogram(pull, push, n_tdc, tdc_range, measurement_cycles, calibration, quarantine,
                    checkpoint, journal, run_id, metrics, name, date, senders) -> None:
    """Per-TDC histograms of the word stream, per measurement or at the end of the run."""
    from pipeline.io.caldir import read_bounds
    from pipeline.stream.fanout import parse_range, worker_reader
    from pipeline.stream.journal import read_range, run_end, run_meta
    from pipeline.stream.stage import run_stage
    from stages.stream import HistogramCore

    a, b = parse_range(tdc_range) if tdc_range else (0, n_tdc)
    bounds = read_bounds(calibration, n_tdc) if calibration else None
    if bounds is not None:
        bounds = bounds.rows(a, b)
    backfill = ended = None
    context = {"run": run_id} if run_id else {}
    if date:
        context["date"] = date
    if journal and run_id:
        meta = run_meta(journal, run_id)
        context.update({k: meta[k] for k in ("t_laser_win_ns", "window_ns") if k in meta})

        def corrupt(first, n, why):  # never folded in: counted as a gap by the core
            err.print(f"{name}: journal words [{first}, {first + n}) skipped: {why}")

        backfill = worker_reader(lambda s, e: read_range(journal, run_id, s, e, corrupt),
                                 n_tdc, (a, b))

        def ended():
            total = run_end(journal, run_id)
            return None if total is None else total // n_tdc * (b - a)
    core = HistogramCore(b - a, bounds, backfill=backfill, tdc_offset=a,
                         measurement_cycles=measurement_cycles, step_id=name,
                         context=context)
    stats = run_stage(core, pull, push, quarantine=quarantine, checkpoint=checkpoint,
                      run_ended=ended, metrics=metrics, name=name,
                      senders=list(senders) or None)
    err.print(f"{name}: received {stats.received}, sent {stats.sent}, rejected "
              f"{dict(stats.rejected)}; backfilled {core.backfilled:,} words, skipped "
              f"{core.duplicates:,} already counted, unfilled gaps {core.gap_words:,}")


@stage.command("range")
@click.option("--pull", required=True, help="Endpoint to bind for input (histograms)")
@click.option("--push", required=True, help="Endpoint to send ranges and histograms to")
@click.option("--calibration", required=True, type=click.Path(exists=True, file_okay=False))
@click.option("--estimator", default="ml", show_default=True)
@click.option("--workers", default=1, show_default=True, help="Histogram workers upstream.")
@click.option("--quarantine", type=click.Path(), default=None)
@_metrics
@_accept
def stage_range(pull, push, calibration, estimator, workers, quarantine, metrics,
                senders) -> None:
    """Ranges of each measurement's histograms with a calibration (eq. 5.4)."""
    from pipeline.io.caldir import load_calibration
    from pipeline.offline.ranging import RangeCore
    from pipeline.stream.stage import run_stage

    core = RangeCore(load_calibration(calibration), estimator)
    stats = run_stage(core, pull, push, quarantine=quarantine, expect_stops=workers,
                      metrics=metrics, name="range", senders=list(senders) or None)
    err.print(f"range: {core.ranged} measurements ranged; rejected {dict(stats.rejected)}"
              + (f"; calibration notes {core.notes}" if core.notes else ""), highlight=False)


@stage.command("sink")
@click.option("--pull", required=True, help="Endpoint to bind for input")
@click.option("--out", required=True, type=click.Path(), help="dataset root")
@click.option("--quarantine", type=click.Path(), default=None)
@click.option("--workers", default=1, show_default=True, help="Stages feeding this sink.")
@_metrics
@_accept
def stage_sink(pull, out, quarantine, workers, metrics, senders) -> None:
    """Parquet datasets (histograms, ranges), Hive-partitioned by date and run."""
    from pipeline.stream.stage import ParquetSink, run_stage

    sink = ParquetSink(out)
    stats = run_stage(sink, pull, None, quarantine=quarantine, expect_stops=workers,
                      metrics=metrics, name="sink", senders=list(senders) or None)
    err.print(f"sink: wrote {sink.files} files; rejected {dict(stats.rejected)}")


@cli.command()
@click.option("--config", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Topology TOML (default: the street scene through 2 workers; see "
                   "pipeline/stream/daemon.py for the keys).")
@click.option("--run", "run_id", default=None, help="Run id (default: from the config).")
def daemon(config, run_id) -> None:
    """Start the stream graph under a supervisor that restarts crashed stages; on exit,
    reconcile the datasets with the journal and write the run's accounting."""
    import signal

    from pipeline.stream.daemon import Supervisor, load_topology

    topo = load_topology(config, run_id)
    sup = Supervisor(topo, log=lambda m: err.print(f"daemon: {m}", highlight=False))
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: sup.stop.set())
    result = sup.run()
    click.echo(json.dumps(result, indent=1))
    if result["failed"]:
        sys.exit(1)


@cli.command()
@click.option("--state", default="data/daemon", show_default=True, type=click.Path(),
              help="The daemon's state directory.")
@click.option("--watch", type=float, default=None, help="Refresh every this many seconds.")
@click.option("--json", "as_json", is_flag=True, help="Print status.json as it is.")
def status(state, watch, as_json) -> None:
    """Live view of a running daemon: per-stage health, rates, queues, restarts."""
    import time as _time

    from rich.live import Live

    path = Path(state) / "status.json"
    if not path.exists():
        raise click.ClickException(f"{path}: no status (is a daemon running with --state "
                                   f"{state}?)")
    if as_json:
        click.echo(path.read_text())
        return
    con = Console(width=None if sys.stdout.isatty() else 160)  # piped: no wrapped columns
    if watch is None:
        con.print(_status_table(json.loads(path.read_text())))
        return
    with Live(_status_table(json.loads(path.read_text())), console=con) as live:
        while True:
            _time.sleep(watch)
            live.update(_status_table(json.loads(path.read_text())))


def _status_table(st: dict):
    import time as _time

    from rich.table import Table

    age = _time.time() - st["updated"]
    state = st["state"] if st["state"] != "running" or age < 5 else \
        f"not updated for {age:.0f} s (daemon gone?)"
    t = Table(title=f"run {st['run']}: {state}")
    for col in ("stage", "health", "pid", "restarts", "received", "sent", "M words/s",
                "queue", "blocked s", "rejected"):
        t.add_column(col)
    for name, s in st["stages"].items():
        rate = s.get("rate_words_s")
        t.add_row(name, s["health"], str(s.get("pid")), str(s["restarts"]),
                  str(s.get("received", "")), str(s.get("sent", "")),
                  f"{rate / 1e6:.1f}" if rate is not None else "",
                  str(st["queue_depth"].get(name, "")), str(s.get("blocked_s", "")),
                  str(s.get("rejected") or ""))
    return t


class _Lazy(click.Group):
    """A command (group) imported only when it is used: ``tcspc --help`` lists it from its
    short help without importing the module (and numba, pyarrow or Prefect with it)."""

    def __init__(self, name: str, load, short_help: str) -> None:
        super().__init__(name)
        self._loader, self._real, self._short = load, None, short_help

    def _load(self) -> click.Command:
        if self._real is None:
            self._real = self._loader()
        return self._real

    def make_context(self, info_name, args, parent=None, **extra):
        return self._load().make_context(info_name, args, parent, **extra)

    def invoke(self, ctx):
        return self._load().invoke(ctx)

    def list_commands(self, ctx):
        real = self._load()
        return real.list_commands(ctx) if isinstance(real, click.Group) else []

    def get_command(self, ctx, name):
        real = self._load()
        return real.get_command(ctx, name) if isinstance(real, click.Group) else None

    def get_short_help_str(self, limit: int = 45) -> str:
        return self._short


def _module_command(module: str, attr: str):
    def load():
        import importlib

        return getattr(importlib.import_module(module), attr)
    return load


_LAZY = {  # name: (module, attribute, short help)
    "calibrate": ("pipeline.cli.calibrate", "calibrate",
                  "Density test, LSB against light, and zero-distance delay."),
    "model": ("pipeline.cli.model", "model",
              "Chapter 2: link budget, ambient light, transmission, prediction, histograms."),
}
#: Short help of the commands added by the layers above through the entry point.
_ENTRY_HELP = {"flow": "Run or serve the Prefect flows (calibration, sweeps, reports).",
               "demo": "The whole story on embedded defaults (what `make demo` runs)."}


def _register() -> None:
    for name, (module, attr, short) in _LAZY.items():
        cli.add_command(_Lazy(name, _module_command(module, attr), short), name)
    # Layers above the pipeline (the flows) add their commands through an entry point, so
    # nothing here imports them (DESIGN.md: nothing imports ``flows``).
    from importlib.metadata import entry_points

    for ep in entry_points(group="tcspc.commands"):
        if ep.name not in cli.commands:
            cli.add_command(_Lazy(ep.name, ep.load, _ENTRY_HELP.get(ep.name, ep.name)),
                            ep.name)


_register()


def main() -> None:
    """Entry point: project errors become one clear line and exit status 2."""
    try:
        cli.main(standalone_mode=False)
    except click.exceptions.Abort:
        err.print("aborted")
        sys.exit(130)
    except click.ClickException as exc:
        exc.show()
        sys.exit(exc.exit_code)
    except Exception as exc:
        from schemas.errors import TcspcError

        if not isinstance(exc, TcspcError | OSError):
            raise
        err.print(f"[red]error:[/red] {exc}", highlight=False)
        sys.exit(2)


if __name__ == "__main__":
    main()
