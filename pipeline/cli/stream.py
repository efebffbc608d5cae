"""``tcspc stage ...``, ``tcspc daemon`` and ``tcspc status``: the stream's commands (each
stage alone, the supervised graph, its health). Loaded when one of them is named."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click
from rich.console import Console
from rich.table import Table

from pipeline.cli.app import _calibration
from pipeline.cli.console import err


@click.group()
@click.option("--insecure", is_flag=True, envvar="TCSPC_INSECURE",
              help="Let a stage on tcp:// run without the run's token and CURVE keys "
                   "($TCSPC_TOKEN_FILE, $TCSPC_CURVE_DIR): anyone who reaches the port may "
                   "then send it messages.")
def stage(insecure) -> None:
    """Run one stage of the stream alone (the graph can span processes and hosts)."""
    from pipeline.cli.app import _one_blas_thread

    # a stage is one core's work, whoever starts it (the daemon, a systemd unit, a shell):
    # numpy's OpenBLAS would start a thread per core whose spinning after each small
    # product takes the cores the other stages need
    _one_blas_thread()


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
    "--journal-compression", type=click.Choice(["zstd-nohit", "zstd", "none"]),
    default="zstd-nohit", show_default=True,
    help="Journal segments as zstd frames of the words less their no-hit pattern "
         "(RUN-N.bin.nhz; `tcspc journal export` gives the raw capture), as zstd frames of "
         "the words (RUN-N.bin.zst; `zstd -d` gives it) or raw (RUN-N.bin).")


_wire = click.option(
    "--wire", type=click.Choice(["sparse", "words"]), default="sparse", show_default=True,
    help="Send the chip's words sparse (only those that are not plain no_hit words, with "
         "their index: a tenth of the bytes at 5 % hits) or whole.")


#: words per batch of a replayed capture (whole cycles; a journal chunk and a message per
#: worker): 4 MiB. Against 1 MiB, the daemon's graph needed 1.77 cores at 110 M words/s
#: instead of 2.15 (a fourth of the messages: the worker 404 M words per CPU-second
#: against 256, the source 198 against 157; docs/performance.md "The daemon at line rate")
REPLAY_BATCH_WORDS = 1 << 20


def _secure(*endpoints) -> None:
    """Refuse a tcp:// endpoint without the run's token and CURVE keys (any host or account
    that reaches the port could feed the stage forged words or a stop) unless --insecure."""
    import os

    from pipeline.stream.curve import CURVE_ENV
    from pipeline.stream.wire import TOKEN_ENV

    ctx = click.get_current_context()
    if ctx.parent is not None and ctx.parent.params.get("insecure"):
        return
    tcp = [e for e in endpoints if e and str(e).startswith("tcp://")]
    missing = [f"${v}" for v in (TOKEN_ENV, CURVE_ENV) if not os.environ.get(v)]
    if tcp and missing:
        raise click.UsageError(
            f"{tcp[0]}: a tcp:// endpoint without {' and '.join(missing)}: anyone who "
            "reaches the port could send this stage messages; set them (`tcspc stage plan` "
            "writes both) or pass `tcspc stage --insecure ...`")


def _run_id(ctx, param, value):
    """--run: a run id becomes a directory name (journal, checkpoints): 1..64 of
    [A-Za-z0-9._-], never '.' or '..'."""
    from pipeline.stream.wire import ID_PATTERN, run_id_from

    if value is not None and not ID_PATTERN.fullmatch(value):
        raise click.BadParameter(f"{value!r}: use 1..64 of [A-Za-z0-9._-], not '.' or '..' "
                                 f"(it becomes a directory name), e.g. {run_id_from(value)!r}")
    return value


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
@click.option("--run", "run_id", default="sim", show_default=True, callback=_run_id)
@click.option("--rate", type=float, default=None, help="Words per second (default: max).")
@click.option("--journal", type=click.Path(), default=None,
              help="Journal the words here before sending them.")
@_journal_compression
@_split
@_metrics
@_date
@_wire
def stage_source_sim(scene_path, cycles, pushes, seed, chip_seed, run_id, rate, journal,
                     journal_compression, split, metrics, date, wire) -> None:
    """The simulator as a source: raw-word batches of SCENE_PATH."""
    _secure(*pushes, metrics)
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
                      metrics=metrics, window_ns=sim.sm.scene.sensor.window_ns, date=date,
                      sparse=wire == "sparse")
    err.print(f"source-sim: sent {sent:,} words")


@stage.command("source-capture")
@click.argument("capture", type=click.Path())
@_push
@click.option("--run", "run_id", default=None, help="Run id (default: the capture's name)",
              callback=_run_id)
@click.option("--rate", type=float, default=None, help="Words per second (default: max).")
@click.option("--journal", type=click.Path(), default=None,
              help="Journal the words here before sending them.")
@_journal_compression
@_split
@_metrics
@_date
@click.option("--repeat", default=1, show_default=True, type=click.IntRange(1),
              help="Replay the capture this many times as one run (soak tests).")
@_wire
def stage_source_capture(capture, pushes, run_id, rate, journal, journal_compression, split,
                         metrics, date, repeat, wire) -> None:
    """Replay a capture into the stream, at a chosen rate or as fast as it is taken."""
    _secure(*pushes, metrics)
    from pipeline.io.capture import Capture
    from pipeline.stream.journal import JournalWriter
    from pipeline.stream.stage import run_source
    from pipeline.stream.wire import run_id_from

    cap = Capture(capture)
    run_id = run_id or run_id_from(cap.name)
    n = cap.meta.n_tdc
    # the words as the file holds them (big-endian: journaled as they are, swapped into
    # the messages) from a ring of 3 buffers: a batch stays valid while the journal,
    # one batch behind, writes it
    cap.chunk_ring = 3

    def replay():
        for k in range(repeat):
            for first, w in cap.iter_chunks(max(1, REPLAY_BATCH_WORDS // n) * n, native=False):
                yield k * cap.n_words + first, w

    batches = _skip_journaled(replay(), journal, run_id)
    jw = (JournalWriter(journal, run_id, n, cap.meta.t_laser_win_ns, cap.meta.window_ns,
                        compression=_compression(journal_compression)) if journal else None)
    sent = run_source(batches, list(pushes), step_id="source", run=run_id,
                      n_tdc=n, t_laser_win_ns=cap.meta.t_laser_win_ns,
                      rate_words_s=rate, journal=jw, split=_ranges(split), metrics=metrics,
                      window_ns=cap.meta.window_ns, date=date, stable=cap.chunk_ring - 1,
                      sparse=wire == "sparse")
    err.print(f"source-capture: sent {sent:,} words")


@stage.command("source-file")
@click.argument("path", type=click.Path(exists=True, dir_okay=False))
@_push
@click.option("--run", "run_id", default=None, help="Run id (default: the file's name)",
              callback=_run_id)
@click.option("--rate", type=float, default=None,
              help="Records per second (default: as fast as they are taken).")
@click.option("--format", "fmt", type=click.Choice(["ptu", "linospad2"]), default=None,
              help="Input format (default: read from the content).")
@click.option("--firmware", type=click.Choice(["2212b", "2212s"]), default="2212b",
              show_default=True, help="LinoSPAD2 firmware.")
@click.option("--journal", type=click.Path(), default=None,
              help="Journal the records here before sending them.")
@_journal_compression
@_split
@_metrics
@_date
def stage_source_file(path, pushes, run_id, rate, fmt, firmware, journal, journal_compression,
                      split, metrics, date) -> None:
    """Replay an instrument's file (PTU T3, LinoSPAD2) into the stream: its raw records, in
    order, as one run; the histogram worker decodes them (``--instrument-file``)."""
    _secure(*pushes, metrics)
    from pipeline.io.formats import (
        instrument_timing_ns,
        instrument_truncation,
        instrument_words,
        resolve_format,
    )
    from pipeline.stream.journal import JournalWriter
    from pipeline.stream.stage import run_source
    from pipeline.stream.wire import run_id_from

    fmt = resolve_format(path, fmt)
    run_id = run_id or run_id_from(Path(path).stem)
    period = instrument_timing_ns(path, fmt)
    damage = instrument_truncation(path, fmt)
    if damage:
        err.print(f"source-file: warning: {damage}; the records before the damage are sent")
    batches = _skip_journaled(instrument_words(path, fmt, 1 << 18), journal, run_id)
    jw = (JournalWriter(journal, run_id, 1, period, period,
                        compression=_compression(journal_compression)) if journal else None)
    sent = run_source(batches, list(pushes), step_id="source", run=run_id, n_tdc=1,
                      t_laser_win_ns=period, rate_words_s=rate, journal=jw,
                      split=_ranges(split), metrics=metrics, window_ns=period, date=date)
    err.print(f"source-file: sent {sent:,} {fmt} records")


@stage.command("ingest-udp")
@click.option("--bind", "bind_addr", default="127.0.0.1:9000", show_default=True,
              help="host:port to listen on (127.0.0.1 unless you choose otherwise)")
@_push
@click.option("--run", "run_id", default="udp", show_default=True, callback=_run_id)
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
@click.option("--gate-ps", type=click.IntRange(1_000, 10_000_000), default=None,
              help="The run's gate (t_laser_win) in ps: a datagram with another is refused "
                   "(default: from a quorum of datagrams).")
@click.option("--first-seq", type=click.IntRange(0, 2**32 - 1), default=None,
              help="The sequence number of the run's first datagram, at cycle 0 (default: "
                   "from a quorum of datagrams).")
@click.option("--peer", "peers", multiple=True,
              help="A sender whose datagrams are read, HOST or HOST:PORT (repeatable; "
                   "default: the run locks onto the sender of its reference).")
@_journal_compression
@_wire
@_split
@_metrics
@_date
def stage_ingest_udp(bind_addr, pushes, run_id, journal, quarantine, idle, n_tdc,
                     reorder_window, max_jump_cycles, gate_ps, first_seq, peers,
                     journal_compression, split, metrics, date, wire) -> None:
    """The FPGA's UDP datagrams (docs/streaming.md) in, journaled raw-word batches out.
    Restarted on a run its journal holds, it takes the run up where the journal has it."""
    _secure(*pushes, metrics)
    import signal
    import threading

    from pipeline.stream.udp import (
        MAX_JUMP_CYCLES,
        REORDER_WINDOW,
        parse_peers,
        run_udp_ingest,
        udp_socket,
    )

    try:
        parse_peers(peers)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--peer") from None
    if not peers:
        err.print("ingest: no --peer ([source] peers): the run locks onto the sender of its "
                  "reference; a second consistent sender makes it incomplete")
    halt = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: halt.set())
    stats = run_udp_ingest(udp_socket(bind_addr), list(pushes), run=run_id, journal=journal,
                           quarantine=quarantine, idle_s=idle, split=_ranges(split),
                           metrics=metrics, date=date, stop=halt,
                           compression=_compression(journal_compression), n_tdc=n_tdc,
                           reorder_window=reorder_window or REORDER_WINDOW,
                           max_jump_cycles=max_jump_cycles or MAX_JUMP_CYCLES,
                           gate_ps=gate_ps, first_seq=first_seq,
                           sparse=wire == "sparse", peers=list(peers) or None)
    err.print(f"ingest: {stats.datagrams} datagrams, {stats.words:,} words, "
              f"{stats.lost_datagrams} lost, {stats.duplicates} duplicates, {stats.late} "
              f"late, {stats.gap_cycles} cycles in gaps, rejected {dict(stats.rejected)}, "
              f"{stats.ring_dropped} dropped by the ring, {stats.conflicts} conflicting, "
              f"{len(stats.resets)} stream restart(s), other senders "
              f"{stats.senders.fields()['other_senders'] if stats.senders else {}}")


@stage.command("histogram")
@click.option("--pull", required=True, help="Endpoint to bind for input")
@click.option("--push", required=True, help="Endpoint to send to")
@click.option("--n-tdc", default=128, show_default=True, help="TDCs per cycle (the chip's).")
@click.option("--tdc-range", default=None, help="This worker's TDCs, FIRST:END (a fan-out).")
@click.option("--measurement-cycles", type=click.IntRange(1), default=None,
              help="Emit a histogram per this many cycles (default: one at the run's end).")
@_calibration
@click.option("--bounds", "bounds_path", type=click.Path(exists=True, dir_okay=False),
              default=None, help="The run's artifact bounds estimated from its capture "
                                 "(STATE/bounds/RUN.json, written by the daemon).")
@click.option("--quarantine", type=click.Path(), default=None)
@click.option("--checkpoint", type=click.Path(), default=None,
              help="Checkpoint file: restored at start, saved after every batch.")
@click.option("--journal", type=click.Path(), default=None,
              help="The source's journal directory, to fill gaps after a restart.")
@click.option("--run", "run_id", default=None, help="Run id of the journal to read.",
              callback=_run_id)
@_metrics
@click.option("--name", default="histogram", show_default=True, help="Name in metrics.")
@_date
@_accept
@click.option("--instrument-file", type=click.Path(exists=True, dir_okay=False), default=None,
              help="The stream is this PTU T3 / LinoSPAD2 file's records (source-file): "
                   "histogram them as that instrument does.")
@click.option("--format", "fmt", type=click.Choice(["ptu", "linospad2"]), default=None,
              help="With --instrument-file: its format (default: from the content).")
@click.option("--firmware", type=click.Choice(["2212b", "2212s"]), default="2212b",
              show_default=True, help="With --instrument-file: LinoSPAD2 firmware.")
def stage_histogram(pull, push, n_tdc, tdc_range, measurement_cycles, calibration,
                    bounds_path, quarantine, checkpoint, journal, run_id, metrics, name, date,
                    senders, instrument_file, fmt, firmware) -> None:
    """Per-TDC histograms of the word stream, per measurement or at the end of the run."""
    _secure(pull, push, metrics)
    from pipeline.io.caldir import read_bounds
    from pipeline.stream.fanout import parse_range, worker_reader
    from pipeline.stream.journal import read_range, run_end, run_meta
    from pipeline.stream.stage import run_stage
    from stages.stream import HistogramCore

    a, b = parse_range(tdc_range) if tdc_range else (0, n_tdc)
    if calibration and bounds_path:
        raise click.UsageError("--calibration or --bounds, not both")
    bounds = read_bounds(calibration, n_tdc) if calibration else None
    if bounds_path:
        from pipeline.stream.bounds import load_bounds

        try:
            bounds = load_bounds(bounds_path, n_tdc)
        except ValueError as exc:
            raise click.UsageError(str(exc)) from None
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
            if total is None:
                return None
            # a worker that heard no message (started before the journal existed, then
            # stopped across the run's end) labels what it fetches with the run's gate
            meta = run_meta(journal, run_id)
            for k in ("t_laser_win_ns", "window_ns"):
                if k in meta:
                    core.context.setdefault(k, meta[k])
            return total // n_tdc * (b - a)
    acc = None
    if instrument_file:
        from pipeline.io.formats import resolve_format
        from pipeline.offline.instruments import instrument_accumulator

        if (a, b) != (0, n_tdc) or measurement_cycles or calibration or bounds_path:
            raise click.UsageError("--instrument-file: one worker over the whole stream, no "
                                   "--measurement-cycles or --calibration")
        acc = instrument_accumulator(instrument_file, resolve_format(instrument_file, fmt),
                                     firmware)
    core = HistogramCore(b - a, bounds, backfill=backfill, tdc_offset=a,
                         measurement_cycles=measurement_cycles, step_id=name,
                         context=context, accumulator=acc)
    stats = run_stage(core, pull, push, quarantine=quarantine, checkpoint=checkpoint,
                      run_ended=ended, metrics=metrics, name=name,
                      senders=list(senders) or None)
    err.print(f"{name}: received {stats.received}, sent {stats.sent}, rejected "
              f"{dict(stats.rejected)}; backfilled {core.backfilled:,} words, skipped "
              f"{core.duplicates:,} already counted, unfilled gaps {core.gap_words:,}")


@stage.command("range", short_help="Ranges of each measurement's histograms with a calibration "
               "(eq. 5.4).")
@click.option("--pull", required=True, help="Endpoint to bind for input (histograms)")
@click.option("--push", required=True, help="Endpoint to send ranges and histograms to")
@click.option("--calibration", required=True, type=click.Path(exists=True, file_okay=False))
@click.option("--estimator", default="ml", show_default=True)
@click.option("--max-returns", type=click.IntRange(min=1), default=3, show_default=True,
              help="Returns (surfaces) a pixel may have.")
@click.option("--workers", default=1, show_default=True, help="Histogram workers upstream.")
@click.option("--quarantine", type=click.Path(), default=None)
@click.option("--spatial", is_flag=True,
              help="Each measurement ranged with its neighbours as --geometry's image "
                   "(docs/ranging.md; the workers' parts of it gathered into its frame).")
@click.option("--geometry", default=None, help="With --spatial: the array's layout.")
@click.option("--hold", type=click.IntRange(min=1), default=8, show_default=True,
              help="With --spatial: measurements held while their workers' parts gather "
                   "(past that the oldest is ranged with the parts it has, flagged).")
@_metrics
@_accept
def stage_range(pull, push, calibration, estimator, max_returns, workers, quarantine,
                spatial, geometry, hold, metrics, senders) -> None:
    """Ranges of each measurement's histograms with a calibration (eq. 5.4)."""
    _secure(pull, push, metrics)
    from pipeline.io.caldir import load_calibration
    from pipeline.offline.ranging import RangeCore
    from pipeline.stream.stage import run_stage

    geom = None
    if spatial or geometry:
        if not (spatial and geometry):
            raise click.UsageError("--spatial and --geometry go together")
        if not 1 <= max_returns <= 4:
            raise click.UsageError("--spatial: --max-returns 1..4")
        from pipeline.io.geometry import load_geometry

        geom = load_geometry(geometry)  # checked before the stage starts
    core = RangeCore(load_calibration(calibration), estimator, max_returns=max_returns,
                     warn=lambda m: err.print(f"range: warning: {m}", highlight=False),
                     spatial=geom, hold=hold)
    stats = run_stage(core, pull, push, quarantine=quarantine, expect_stops=workers,
                      metrics=metrics, name="range", senders=list(senders) or None)
    err.print(f"range: {core.ranged} measurements ranged; rejected {dict(stats.rejected)}"
              + (f"; calibration notes {core.notes}" if core.notes else "")
              + (f"; chip check {core.chip_checks}" if core.chip_checks else "")
              + (f"; {core.incomplete_frames} frames without every worker's part"
                 if core.incomplete_frames else "")
              + (f"; {core.gather.duplicates} parts sent again dropped"
                 if core.gather is not None and core.gather.duplicates else ""),
              highlight=False)


@stage.command("sink")
@click.option("--pull", required=True, help="Endpoint to bind for input")
@click.option("--out", required=True, type=click.Path(), help="dataset root")
@click.option("--quarantine", type=click.Path(), default=None)
@click.option("--workers", default=1, show_default=True, help="Stages feeding this sink.")
@click.option("--pointcloud", type=click.Choice(["las", "ply", "pcd", "mcap"]), default=None,
              help="Each ranges message also as a point cloud (docs/geometry.md).")
@click.option("--geometry", default=None, help="With --pointcloud: the geometry.")
@_metrics
@_accept
def stage_sink(pull, out, quarantine, workers, pointcloud, geometry, metrics, senders) -> None:
    """Parquet datasets (histograms, ranges), Hive-partitioned by date and run."""
    _secure(pull, metrics)
    from pipeline.stream.stage import ParquetSink, run_stage

    cloud = None
    if pointcloud:
        if not geometry:
            raise click.UsageError("--pointcloud needs --geometry")
        from pipeline.io.geometry import load_geometry

        cloud = (pointcloud, load_geometry(geometry))  # checked before the stage starts
    sink = ParquetSink(out, cloud=cloud)
    stats = run_stage(sink, pull, None, quarantine=quarantine, expect_stops=workers,
                      metrics=metrics, name="sink", senders=list(senders) or None)
    err.print(f"sink: wrote {sink.files} files; rejected {dict(stats.rejected)}")


@stage.command("plan", short_help="Each stage as a service on its host: one NAME.env per "
                                  "stage (systemd).")
@click.option("--config", required=True, type=click.Path(exists=True, dir_okay=False),
              help="The topology TOML (tcp:// endpoints for stages on other hosts).")
@click.option("--run", "run_id", default=None, help="Run id (default: from the config).")
@click.option("--out", required=True, type=click.Path(file_okay=False),
              help="Directory for one NAME.env per stage (systemd's EnvironmentFile).")
@click.option("--overwrite", is_flag=True, help="Replace NAME.env files already there.")
def plan(config, run_id, out, overwrite) -> None:
    """Each stage of the graph as a service: writes OUT/NAME.env for the systemd template
    tcspc-stage@.service (docs/systemd/, docs/operations.md): the stage's arguments,
    the run's token file and, with CURVE on, the key directory (both made in the state
    directory now; copy them to the stage's host at the same path)."""
    import shlex

    from pipeline.stream.daemon import build, run_token
    from pipeline.stream.state import make_private, refuse_links
    from pipeline.stream.topology import load_topology
    from pipeline.stream.wire import TOKEN_ENV

    topo = load_topology(config, run_id)
    stages = [(p.name, p.argv[p.argv.index("stage") + 1:])  # after `... pipeline.cli stage`
              for p in build(topo)]
    for name, args in stages:  # all checked before any file is written
        if any(any(c.isspace() for c in a) for a in args):
            raise click.ClickException(f"{name}: an argument holds white space, which "
                                       "systemd's $TCSPC_STAGE_ARGS would split: "
                                       + shlex.join(args))
    from pipeline.io.atomic import check_output

    for name, _ in stages:  # (the output policy: docs/design.md "Outputs")
        check_output(Path(out) / f"{name}.env", overwrite=overwrite)
    # the daemon's checks: 0700, ours, no links, no other account's folder above it
    make_private(topo.state)
    refuse_links(topo.state)
    for d in ("logs", "journal", f"checkpoints/{topo.run}"):
        (topo.state / d).mkdir(parents=True, exist_ok=True)
    token, _ = run_token(topo.state, topo.run)
    env = {TOKEN_ENV: str(token.resolve())}
    if topo.curve_on:
        from pipeline.stream.curve import CURVE_ENV, ensure_keys

        env[CURVE_ENV] = str(ensure_keys(topo.state).resolve())
    Path(out).mkdir(parents=True, exist_ok=True)
    for name, args in stages:
        lines = [f"TCSPC_STAGE_ARGS={' '.join(args)}", *(f"{k}={v}" for k, v in env.items())]
        (Path(out) / f"{name}.env").write_text("\n".join(lines) + "\n")
        click.echo(f"{name}: {Path(out) / f'{name}.env'}  (tcspc stage {args[0]})")
    err.print(f"CURVE {'on' if topo.curve_on else 'off'}; run {topo.run}; start each with "
              f"`systemctl start tcspc-stage@NAME` on its host, the source last", highlight=False)


@click.command()
@click.option("--config", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Topology TOML (default: the street scene through 2 workers; every "
                   "key: docs/operations.md, \"Every key of a topology\").")
@click.option("--run", "run_id", default=None, help="Run id (default: from the config).")
@click.option("--log-json", is_flag=True, help="Log as JSON lines (ts, level, stage, msg) "
              "instead of text (also [log] format = \"json\").")
@click.option("--unit", "print_unit", is_flag=True, help="Print a systemd unit (Type=notify, "
              "a watchdog) that runs this daemon with this --config, and exit.")
def daemon(config, run_id, log_json, print_unit) -> None:
    """Start the stream graph under a supervisor that restarts crashed stages; on exit,
    reconcile the datasets with the journal and write the run's accounting. Exit 0: the run
    finished, every word in; 1: failed; 3: incomplete (unbalanced, a measurement withheld,
    no reconciliation, input lost: the problems are printed); 130 (Ctrl-C) or 143
    (SIGTERM): interrupted, resumable with the same --run."""
    import signal

    if print_unit:
        from pipeline.stream.systemd import daemon_unit

        click.echo(daemon_unit(config, run_id), nl=False)
        return
    # a stop asked for before the supervisor exists is kept: a daemon started with SIGINT
    # ignored (a background job of a non-interactive shell) has no handler of Python's
    # own, and one that came before the supervisor's was lost (the run went on to
    # "finished", exit 0); before the supervisor it ends the command, after it the run
    early: list[int] = []
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda signum, _: early.append(signum))
    from pipeline.stream import forkstart

    forkstart.warm_for(config)  # first: the stages' server imports while the daemon does
    from pipeline.stream.daemon import Supervisor, exit_code
    from pipeline.stream.logfmt import daemon_log
    from pipeline.stream.topology import load_topology

    topo = load_topology(config, run_id)
    log = daemon_log("json" if log_json else topo.log_format)
    if early:  # (nothing started: no run to stop or resume)
        err.print("aborted")
        sys.exit(128 + early[0])
    sup = Supervisor(topo, log=log)
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda signum, _: sup.interrupt(signum))
    for signum in early:  # (between the check and the handler)
        sup.interrupt(signum)
    result = sup.run()
    for sig in (signal.SIGTERM, signal.SIGINT):  # the run is over: its exit status stands
        signal.signal(sig, signal.SIG_IGN)
    click.echo(json.dumps(result, indent=1))
    words = (result.get("accounting") or {}).get("words_in", 0)
    state = result["state"]
    if state == "interrupted":
        log(f"run {topo.run} interrupted ({result['interrupted']}) after "
            f"{words:,} words; resume it with `tcspc daemon"
            f"{' --config ' + str(config) if config else ''} --run {topo.run}`")
    elif state == "incomplete":
        log(f"run {topo.run} incomplete: " + "; ".join(result["problems"]))
    elif state == "finished":
        log(f"run {topo.run} finished: {words:,} words, balanced")
    sys.exit(exit_code(result))


@click.command()
@click.option("--config", type=click.Path(exists=True, dir_okay=False), default=None,
              help="The run's topology TOML (default: the daemon's default topology).")
@click.option("--run", "run_id", required=True, help="The run to reconcile.")
def reconcile(config, run_id) -> None:
    """Finish or check a run offline, no daemon running: its datasets reconciled with its
    journal (a measurement missing or partial rebuilt from the journal), its accounting
    written and printed with what is missing. Run it twice: the same result. Exit 0: the
    run finished, every word in, balanced; 3: incomplete or interrupted (the problems
    printed); 2: a daemon holds the state, or no journal of the run."""
    from pipeline.stream.daemon import reconcile_offline
    from pipeline.stream.topology import load_topology

    topo = load_topology(config, run_id)
    result = reconcile_offline(topo)
    click.echo(json.dumps(result, indent=1))
    rec, acc = result["reconciled"], result["accounting"]
    for part in rec.get("rebuilt", []):
        err.print(f"rebuilt from the journal: {part['file']} ({part['why']})", highlight=False)
    for m, t in rec.get("recomputed", []):
        err.print(f"recomputed from the journal: measurement {m}, TDCs from {t} (missing "
                  "from the datasets)", highlight=False)
    missing = rec.get("unrecoverable", []) + rec.get("corrupt", [])
    if missing:
        err.print(f"missing measurements [measurement, first TDC]: {missing}",
                  highlight=False)
    for line in result["notes"] + result["problems"]:
        err.print(f"run {topo.run}: {line}", highlight=False)
    err.print(f"run {topo.run} {result['state']}: {acc['classified']:,} of "
              f"{acc['words_in']:,} journaled words classified in the datasets, "
              f"{acc['withheld']:,} withheld; accounting {acc['path']}", highlight=False)
    sys.exit(0 if result["state"] == "finished" else 3)


@click.command()
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
        click.echo(path.read_text().rstrip())  # (padded: see write_status_file)
        return
    # piped: no wrapped columns; markup off: stage names and reasons are printed as they are
    con = Console(width=None if sys.stdout.isatty() else 160, markup=False)
    if watch is None:
        con.print(_status_table(json.loads(path.read_text())))
        return
    with Live(_status_table(json.loads(path.read_text())), console=con) as live:
        while True:
            _time.sleep(watch)
            live.update(_status_table(json.loads(path.read_text())))


def _status_table(st: dict):
    import time as _time


    age = _time.time() - st["updated"]
    state = st["state"] if st["state"] != "running" or age < 5 else \
        f"not updated for {age:.0f} s (daemon gone?)"
    from rich.text import Text

    t = Table(title=f"run {st['run']}: {state}",
              caption=Text("; ".join(st.get("problems") or [])) or None)
    for col in ("stage", "health", "pid", "restarts", "received", "sent", "M words/s",
                "queue", "blocked s", "rejected"):
        t.add_column(col)
    tot = st.get("totals") or {}  # the run's restarts and rejections, across daemons
    totals, rejected = tot.get("restarts") or {}, tot.get("rejected") or {}
    for name, s in st["stages"].items():
        rate = s.get("rate_words_s")
        t.add_row(name, s["health"], str(s.get("pid")), str(totals.get(name, s["restarts"])),
                  str(s.get("received", "")), str(s.get("sent", "")),
                  f"{rate / 1e6:.1f}" if rate is not None else "",
                  str(st["queue_depth"].get(name, "")), str(s.get("blocked_s", "")),
                  str(rejected.get(name) or s.get("rejected") or ""))
    return t


