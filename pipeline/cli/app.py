"""The ``tcspc`` command line (docs/design.md "Command line")."""

from __future__ import annotations

import gc
import os
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import click

from pipeline.cli.console import (  # noqa: F401 (re-exported)
    InternalError,
    console,
    err,
    error,
    out,
    warn,
)

# Heavy modules (numpy, pyarrow, numba, scipy) are imported in the commands that use them:
# `tcspc --help` and a command's own --help stay fast (tests/pipeline/cli/test_cli.py checks).
# So are rich's progress bar and table (20 ms): a quiet command does not draw them.


def _one_blas_thread() -> None:
    """numpy's OpenBLAS starts a thread per core when numpy is first imported, and they
    spin before they sleep: 50-130 ms of CPU of a `histogram` or `decode` command's
    0.2-0.5 s on this 2-core VM (more with more cores; docs/performance.md), for linear
    algebra those commands never do. Asked for one thread before numpy loads (a user's
    own OPENBLAS_NUM_THREADS is kept)."""
    if "numpy" not in sys.modules:  # (afterwards it would change nothing but children)
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


@contextmanager
def _progress(total: int, passes: int, quiet: bool, label: str, unit: str = "words"):
    """A progress bar over ``total`` items (words or cycles), all passes, on stderr."""
    if quiet:
        yield lambda n: None
        return
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        ProgressColumn,
        TextColumn,
        TimeRemainingColumn,
    )

    class _RateColumn(ProgressColumn):
        """Items per second, in millions."""

        def render(self, task):
            speed = task.finished_speed or task.speed
            return TextColumn("").render(task) if speed is None else f"{speed / 1e6:.1f} M/s"

    cols = [TextColumn(label, style="bold", markup=False), BarColumn(), MofNCompleteColumn(),
            TextColumn(unit), _RateColumn(), TimeRemainingColumn()]
    with Progress(*cols, console=err.get(), transient=False) as bar:
        task = bar.add_task(label, total=total * passes)
        yield lambda n: bar.advance(task, n)


def _summary(counts, n_words: int, seconds: float, bounds_source: str,
             verb: str = "read") -> None:
    from rich.table import Table

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
        raise InternalError(f"accounting error: classes add up to {total}, "
                            f"{n_words} words were read")


def _check_cut(cap, out: str, allow: bool) -> None:
    """A capture cut short is treated as a PTU file cut short: its whole cycles written,
    the output flagged ``tcspc.truncated``, exit 3 unless --allow-truncated."""
    if cap.truncated:
        from pipeline.cli.instruments import Truncated

        if not allow:
            raise Truncated(f"{cap.truncated}: {out} holds its {cap.n_words // cap.meta.n_tdc:,}"
                            " whole cycles, flagged truncated in its metadata; "
                            "--allow-truncated accepts that (exit 0)")
        warn(f"{cap.truncated} (--allow-truncated: its whole cycles written, flagged "
             "tcspc.truncated)")


def _input_bytes(path: str) -> int:
    """The size of an input file (a capture's words), 0 where it cannot be told."""
    from pipeline.io.capture import capture_paths

    for p in (Path(path), capture_paths(path)[0]):
        if p.is_file():
            return p.stat().st_size
    return 0


def _warn_uncertain(bounds) -> None:
    """Estimated bounds the data cannot vouch for are said, even with --quiet."""
    if bounds.uncertain.any():
        warn(f"artifact bounds uncertain on {int(bounds.uncertain.sum())} TDC(s): "
             f"{bounds.describe()}; give --calibration for exact bounds")


def _open(path: str, calibration: str | None):
    """The capture (read to its last whole cycle when cut short: :func:`_check_cut`) and
    the calibration's bounds, if one is given."""
    from pipeline.io.capture import Capture

    cap = Capture(path, allow_truncated=True)
    if not calibration:  # (caldir imports pyarrow.parquet and scipy: not needed here)
        return cap, None
    from pipeline.io.caldir import read_bounds

    return cap, read_bounds(calibration, cap.meta.n_tdc)


#: the exit statuses of every command (docs/design.md "Exit codes" has the table of each
#: command's; tests/pipeline/cli/test_exit_codes.py holds them)
EXIT_OK, EXIT_INTERNAL, EXIT_BAD_INPUT, EXIT_INCOMPLETE, EXIT_INTERRUPTED = 0, 1, 2, 3, 130


def _one_line_usage(exc: click.UsageError) -> str:
    """click's three-line usage block as one line: the message and where help is."""
    where = exc.ctx.command_path if exc.ctx is not None else "tcspc"
    return f"{exc.format_message()} (see: {where} --help)"


def run_command(call) -> int:
    """Run ``call`` (a command line) and return its exit status, every error as one line
    on stderr: 2 for bad input or configuration (a usage error, a ``ClickException``, a
    project error, an OSError), the status an error carries where it has its own (3 for
    an incomplete result), 130 when interrupted, 1 for anything else: a bug, said as one
    line too (``TCSPC_TRACEBACK=1`` shows the traceback)."""
    try:
        rv = call()
    except SystemExit as exc:  # a command's own status (the daemon's, a flow's)
        if exc.code is None or isinstance(exc.code, int):
            return exc.code or EXIT_OK
        error(str(exc.code))  # (sys.exit("message"): said, as Python would)
        return EXIT_INTERNAL
    except (click.exceptions.Abort, KeyboardInterrupt):
        err.print("aborted")
        return EXIT_INTERRUPTED
    except click.exceptions.Exit as exc:
        return exc.exit_code
    except click.UsageError as exc:
        if type(exc).__name__ == "NoArgsIsHelpError":  # a group named alone: its help
            exc.show()
        else:
            error(_one_line_usage(exc))
        return EXIT_BAD_INPUT
    except click.ClickException as exc:
        error(exc.format_message())
        # a plain ClickException is a refusal of the user's input: 2 (click's own default,
        # 1, is kept for internal errors only); subclasses carry their own (3: incomplete)
        return EXIT_BAD_INPUT if type(exc) is click.ClickException else exc.exit_code
    except Exception as exc:
        from schemas.errors import TcspcError

        if isinstance(exc, TcspcError | OSError):
            error(str(exc))  # one line, the text as it is (markup off)
            return EXIT_BAD_INPUT
        if os.environ.get("TCSPC_TRACEBACK"):
            raise
        error(f"internal error (a bug; TCSPC_TRACEBACK=1 shows where): "
              f"{type(exc).__name__}: {exc}")
        return EXIT_INTERNAL
    return rv if isinstance(rv, int) else EXIT_OK


class _Root(click.Group):
    """The root group: the entry points' commands are read on first need, and every error
    becomes one line and the exit status of the contract (:func:`run_command`), whoever
    calls the group (the ``tcspc`` script, click's test runner)."""

    entry_points_read = False

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True,
             **extra):
        code = run_command(lambda: super(_Root, self).main(
            args, prog_name, complete_var, standalone_mode=False, **extra))
        if standalone_mode:
            sys.exit(code)
        return code

    def get_command(self, ctx, name):
        if name not in self.commands:
            _register_entry_points()
        return super().get_command(ctx, name)

    def list_commands(self, ctx):
        _register_entry_points()
        return super().list_commands(ctx)


@click.group(cls=_Root, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="tcspc-lidar")
def cli() -> None:
    """tcspc-lidar: raw SPAD/TDC words to calibrated distances."""


_calibration = click.option("--calibration", "calibration", type=click.Path(exists=True),
                            help="Calibration directory (Nmin/Nmax per TDC). Without it the "
                                 "artifact bounds are estimated from the capture itself.")
_engine = click.option("--engine", type=click.Choice(["numba", "numpy"]), default=None,
                       help="Hot-path engine (default: numba where installed).")
_quiet = click.option("-q", "--quiet", is_flag=True, help="No progress bar or summary.")
_format = click.option("--format", "fmt", type=click.Choice(["tcspc", "ptu", "linospad2"]),
                       default=None, help="Input format (default: read from the content).")
_allow_truncated = click.option(
    "--allow-truncated", is_flag=True,
    help="A capture, PTU or LinoSPAD2 file cut short: exit 0 (default: the whole cycles or "
         "records before the damage are written, flagged truncated, and the command exits "
         "3).")
_overwrite = click.option(
    "--overwrite", is_flag=True,
    help="Replace an existing output of the same kind (never a file or directory of "
         "another kind; without it an existing output is refused before any work).")


def check_out(path, kind: str = "file", overwrite: bool = False, **how):
    """The output policy, at the door (pipeline.io.atomic.check_output)."""
    from pipeline.io.atomic import check_output

    return check_output(path, kind, overwrite=overwrite, **how)


#: what `tcspc decode` may write: each input format's events (or Photon-HDF5)
DECODED = ("decoded_events", "ptu_t2_events", "ptu_t3_events", "linospad2_events")

_firmware = click.option("--firmware", type=click.Choice(["2212b", "2212s"]), default="2212b",
                         show_default=True, help="LinoSPAD2 firmware (pixel mapping).")


@cli.command()
@click.argument("capture", type=click.Path())
@click.option("--out", required=True, type=click.Path(),
              help="events.parquet to write (a PTU file: FILE.h5 writes Photon-HDF5)")
@click.option("--include-no-hit", is_flag=True,
              help="Also write no_hit words as rows (they are always counted).")
@_calibration
@_engine
@_format
@_firmware
@_allow_truncated
@_overwrite
@_quiet
def decode(capture, out, include_no_hit, calibration, engine, fmt, firmware, allow_truncated,
           overwrite, quiet) -> None:
    """Decode CAPTURE into an events parquet file.

    A tcspc capture (NAME.bin) gives decoded_events; a PTU file its photons and markers
    (T2: channel and absolute time in ps; T3: channel, sync number, dtime); a LinoSPAD2
    file its pixel words (cycle, TDC, pixel, code, fine code).
    """
    _one_blas_thread()
    from pipeline.cli import instruments

    fmt = instruments.detect(capture, fmt)
    h5 = Path(out).suffix.lower() in (".h5", ".hdf5")  # Photon-HDF5 (a PTU file's photons)
    # (the events take about as much room as the words or records they come from)
    check_out(out, overwrite=overwrite, fmt="hdf5" if h5 else "parquet",
              schema=None if h5 else DECODED, expected_bytes=_input_bytes(capture))
    if fmt != "tcspc":
        _not_for_instruments(fmt, calibration=calibration, include_no_hit=include_no_hit)
        instruments.decode(capture, fmt, out, firmware, quiet, allow_truncated)
        return
    from pipeline.offline.datapath import decode_capture

    cap, bounds = _open(capture, calibration)
    t0 = time.perf_counter()
    with _progress(cap.n_words, 1 + (bounds is None), quiet, "decode") as step:
        counts, bounds = decode_capture(cap, out, bounds, include_no_hit, engine, step)
    if not quiet:
        _summary(counts, cap.n_words, time.perf_counter() - t0, bounds.describe())
        err.print(f"wrote {out}")
    _warn_uncertain(bounds)
    _check_cut(cap, out, allow_truncated)


@cli.command()
@click.argument("capture", type=click.Path())
@click.option("--out", required=True, type=click.Path(), help="hist.parquet to write")
@click.option("--measurement", default=None, help="Measurement name (default: capture name)")
@_calibration
@_engine
@_format
@_firmware
@click.option("--by", type=click.Choice(["tdc", "pixel"]), default="tdc", show_default=True,
              help="LinoSPAD2: a row per TDC (64) or per pixel (256).")
@_allow_truncated
@_overwrite
@_quiet
def histogram(capture, out, measurement, calibration, engine, fmt, firmware, by,
              allow_truncated, overwrite, quiet) -> None:
    """Histograms of CAPTURE, a row per TDC (histograms dataset).

    A tcspc capture: first-stage codes of its hit words. A PTU T3 file: dtime codes, a row
    per input channel. A LinoSPAD2 file: fine codes, a row per TDC or pixel (--by).
    """
    _one_blas_thread()
    from pipeline.cli import instruments

    fmt = instruments.detect(capture, fmt)
    check_out(out, overwrite=overwrite, schema="histograms")
    if fmt != "tcspc":
        _not_for_instruments(fmt, calibration=calibration)
        instruments.histogram(capture, fmt, out, measurement, firmware, by, quiet,
                              allow_truncated)
        return
    from pipeline.offline.datapath import histogram_capture, write_histograms

    cap, bounds = _open(capture, calibration)
    t0 = time.perf_counter()
    with _progress(cap.n_words, 1, quiet, "histogram") as step:
        state, bounds = histogram_capture(cap, bounds, engine, step,
                                          log=(lambda m: None) if quiet else
                                          (lambda m: err.print(f"histogram: {m}")))
    write_histograms(state, measurement or cap.name, out,
                     {"capture": cap.bin_path, "bounds": bounds.describe(),
                      **({"truncated": True} if cap.truncated else {})})
    if not quiet:
        _summary(state.class_counts.sum(axis=1), cap.n_words, time.perf_counter() - t0,
                 bounds.describe())
        err.print(f"wrote {out}")
    _warn_uncertain(bounds)
    _check_cut(cap, out, allow_truncated)


@cli.command()
@click.argument("out", type=click.Path())
@click.option("--cycles", default=40_000, show_default=True, type=click.IntRange(1))
@click.option("--n-tdc", default=128, show_default=True, type=click.IntRange(1, 256))
@click.option("--hit-prob", default=0.05, show_default=True, type=click.FloatRange(0, 1))
@click.option("--peak-code", default=300.0, show_default=True)
@click.option("--seed", default=0, show_default=True)
@_overwrite
def pattern(out, cycles, n_tdc, hit_prob, peak_code, seed, overwrite) -> None:
    """Write a synthetic capture OUT(.bin) with a known class mix (not the simulator).

    Its sidecar's truth holds the intended class counts, so decode and histogram can be
    checked against it.
    """
    from pipeline.io.capture import CaptureWriter
    from schemas import WORD_CLASSES
    from stages.testpattern import pattern_words

    check_out(out, "capture", overwrite, option="OUT", expected_bytes=4 * cycles * n_tdc)
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
        from rich.text import Text

        out.print(Text.assemble((spec.name, "bold"), f" {spec.version}"), highlight=False)
        out.print(str(spec.schema), markup=False, highlight=False)


@cli.command()
@click.argument("scene_path", type=click.Path(exists=True, dir_okay=False))
@click.option("--cycles", default=40_000, show_default=True, type=click.IntRange(1))
@click.option("--out", required=True, type=click.Path(), help="NAME.bin to write")
@click.option("--seed", default=0, show_default=True, help="Seed of the photons.")
@click.option("--chip-seed", default=1, show_default=True, help="Seed of the chip's "
              "LSB, INL and second-stage parameters (the same chip across captures).")
@click.option("--engine", type=click.Choice(["fast", "reference"]), default=None,
              help="Default: fast, or reference when a target moves or a pixel sees "
                   "several surfaces.")
@click.option("--malformed-rate", default=0.0, show_default=True,
              type=click.FloatRange(0, 1), help="Fraction of words to corrupt (markers).")
@click.option("--invalid-rate", default=0.0, show_default=True,
              type=click.FloatRange(0, 1), help="Fraction of words given a bubble code.")
@click.option("--ideal-tdc", is_flag=True, help="No INL/DNL and no artifact.")
@_overwrite
@_quiet
def simulate(scene_path, cycles, out, seed, chip_seed, engine, malformed_rate, invalid_rate,
             ideal_tdc, overwrite, quiet) -> None:
    """Simulate SCENE_PATH: a raw capture whose sidecar holds the truth."""
    from pipeline.offline.simulate import simulate_capture
    from stages.models.scene import load_scene

    scene = load_scene(scene_path)  # every problem of the file, before anything starts
    check_out(out, "capture", overwrite,
              expected_bytes=4 * cycles * scene.sensor.n_pixels)  # (a word a TDC a cycle)
    t0 = time.perf_counter()
    with _progress(cycles, 1, quiet, "simulate", "cycles") as step:
        meta, sim = simulate_capture(scene, cycles, out, seed=seed, chip_seed=chip_seed,
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
@click.option("--calibration", default=None, type=click.Path(exists=True, file_okay=False),
              help="Calibration directory (a tcspc capture needs one; generic histograms "
                   "take one from `calibrate distance`).")
@click.option("--out", required=True, type=click.Path(), help="ranges.parquet to write")
@click.option("--estimator", type=click.Choice(["ml", "fast", "matched", "centroid", "gaussfit"]),
              default="ml", show_default=True)
@click.option("--irf-ps", type=float, default=None,
              help="Instrument response sigma (default: measured with the delay, else 1 LSB).")
@click.option("--p-fa", default=1e-3, show_default=True, help="False-alarm probability.")
@click.option("--delay-ps", type=float, default=None,
              help="PTU T3: the system delay (time of a zero-distance return after the sync).")
@click.option("--zero", type=click.Path(exists=True), default=None,
              help="PTU T3 or generic histograms: a zero-distance file (or its histograms) "
                   "to measure the delay on (with --spatial: ranged with the neighbours, "
                   "and the response behind a return measured on it too, which a further "
                   "return must then stand above).")
@click.option("--gate", default=None, help="PTU T3: only returns in LO:HI ns after the sync.")
@click.option("--max-returns", type=click.IntRange(min=1), default=None,
              help="Returns (surfaces) a pixel may have, each with its own detection "
                   "[default: 3 on a tcspc capture and on generic histograms with a "
                   "--calibration from `calibrate distance` (its measured response, tail "
                   "and all, is subtracted before the next is searched); 1 on a PTU T3 "
                   "file (more: with --zero its returns are the measured response; with "
                   "--delay-ps only a warning, the search's tails being Gaussian) and on "
                   "generic histograms with --delay-ps (more: Gaussian masks of --irf-ps "
                   "or of the response measured on the returns); 3 on generic histograms "
                   "with --zero (its returns are the measured response)].")
@click.option("--allow-truncated", is_flag=True,
              help="A capture or PTU T3 file (or a --zero file) cut short: range it anyway, "
                   "flagged tcspc.truncated in the output (without it: nothing written, "
                   "exit 3).")
@click.option("--spatial", is_flag=True,
              help="Histograms as an image (generic ones' row/col columns or --geometry; a "
                   "tcspc capture's TDCs by --geometry, each TDC's calibrated axis mapped "
                   "onto one): each pixel ranged with its neighbours, for few photons in "
                   "strong background (docs/ranging.md); generic histograms need "
                   "--irf-ps and --delay-ps or --zero, a capture --calibration.")
@click.option("--geometry", default=None,
              help="With --spatial: the array's layout (docs/geometry.md).")
@click.option("--force", is_flag=True,
              help="A tcspc capture whose code-density pattern is not the --calibration's "
                   "chip's: range it anyway, every row flagged (without it: nothing "
                   "written, exit 2; docs/calibration.md).")
@_format
@_overwrite
@_quiet
def range_cmd(capture, calibration, out, estimator, irf_ps, p_fa, delay_ps, zero, gate,
              max_returns, allow_truncated, spatial, geometry, force, fmt, overwrite,
              quiet) -> None:
    """Distance per pixel (eq. 5.4) with uncertainty and a detection decision.

    CAPTURE is a tcspc capture (with --calibration), or a PicoQuant T3 file or its
    histograms (with --delay-ps or --zero): a PicoQuant board's dtime bins are calibrated
    by its maker, so no INL is applied; the output says so. A pixel may see up to
    --max-returns surfaces (a window, a fence): a row each, return_index 0 the strongest
    (--spatial: the surface the neighbours hold before a weaker lone detection).
    Generic histograms (any instrument's, docs/instruments_generic.md) take
    --calibration from `calibrate distance`, --delay-ps or --zero; the output names the
    instrument response and the pile-up correction used (up to 3 returns a row with a
    calibration or --zero, one with --delay-ps unless --max-returns asks for more).
    """
    check_out(out, overwrite=overwrite, schema="ranges")
    try:
        if (spatial or geometry) and calibration is not None and _is_capture(capture, fmt):
            # a chip's capture: each TDC's INL axis mapped onto one (docs/ranging.md)
            if not (spatial and geometry):
                raise click.UsageError("a tcspc capture's --spatial needs --geometry (its "
                                       "TDCs' places), and --geometry --spatial")
            from pipeline.io.geometry import load_geometry

            _range(capture, calibration, out, "spatial", irf_ps, p_fa, delay_ps, zero, gate,
                   max_returns, fmt, quiet, allow_truncated, force,
                   spatial=load_geometry(geometry))
            return
        if spatial or geometry:
            from pipeline.cli.export import range_spatial

            range_spatial(capture, out, spatial, geometry, irf_ps, p_fa, delay_ps,
                          max_returns, quiet, calibration=calibration, zero=zero, gate=gate)
            return
        _range(capture, calibration, out, estimator, irf_ps, p_fa, delay_ps, zero, gate,
               max_returns, fmt, quiet, allow_truncated, force)
    except ValueError as exc:  # an argument or a histogram the estimators refuse: one line
        from schemas.errors import TcspcError

        if isinstance(exc, TcspcError):  # (main prints ours)
            raise
        from pipeline.cli.instruments import BadInput

        raise BadInput(str(exc)) from exc


def _is_capture(capture, fmt) -> bool:
    from pipeline.cli import instruments

    return instruments.detect(capture, fmt, histograms=True) == "tcspc"


def _range(capture, calibration, out, estimator, irf_ps, p_fa, delay_ps, zero, gate,
           max_returns, fmt, quiet, allow_truncated=False, force=False,
           spatial=None) -> None:
    from pipeline.cli import instruments
    from stages.ranging.validation import check_delay, check_p_fa, check_sigma

    try:
        check_p_fa(p_fa)
        if irf_ps is not None:
            check_sigma(irf_ps, name="--irf-ps")
        if delay_ps is not None:
            if delay_ps != delay_ps:  # NaN: "no delay" inside, not a value to give
                raise ValueError(f"--delay-ps must be finite, found {delay_ps}")
            check_delay(delay_ps, "--delay-ps")
    except ValueError as exc:
        raise instruments.BadInput(str(exc)) from exc
    from pipeline.offline.ranging import SIGMA_NOTE

    if estimator in SIGMA_NOTE:
        warn(SIGMA_NOTE[estimator] + " (ml and fast's cover)")
    fmt = instruments.detect(capture, fmt, histograms=True)
    if force and fmt != "tcspc":
        raise click.UsageError("--force is for a tcspc capture with --calibration (its chip "
                               "check); not for a " + fmt + " file")
    if fmt == "histograms" and instruments.is_generic(capture):
        # several returns need the returns' measured response (tail and all), which a
        # calibration from `calibrate distance` holds: 3 by default with one, else 1
        instruments.range_generic(capture, out, calibration, delay_ps, zero, gate, estimator,
                                  irf_ps, p_fa, quiet, max_returns)
        return
    if fmt != "tcspc":
        if calibration:
            raise click.UsageError("--calibration is the thesis chip's; an instrument's "
                                   "file takes --delay-ps or --zero")
        # further returns need the measured response, which --zero's file gives: 3 by
        # default with it, else 1 (and a warning when more are asked)
        instruments.range_instrument(capture, fmt, out, delay_ps, zero, gate, estimator,
                                     irf_ps, p_fa, "2212b", quiet, max_returns,
                                     allow_truncated)
        return
    if calibration is None:
        raise click.UsageError("a tcspc capture needs --calibration")
    if delay_ps is not None or zero is not None or gate is not None:
        raise click.UsageError("--delay-ps, --zero and --gate are for an instrument's file; "
                               "a tcspc capture takes its delay from --calibration")
    from pipeline.io.caldir import load_calibration
    from pipeline.io.capture import Capture
    from pipeline.offline.ranging import range_capture

    t0 = time.perf_counter()
    calib = load_calibration(calibration)
    cap = Capture(capture, allow_truncated=True)
    if cap.truncated and not allow_truncated:  # as a PTU file cut short: nothing written
        from pipeline.cli.instruments import Truncated

        raise Truncated(f"{cap.truncated}: its ranges would come from part of a measurement; "
                        "nothing written (--allow-truncated ranges it anyway, flagged "
                        "tcspc.truncated in the output)")
    if cap.truncated:
        warn(cap.truncated + " (--allow-truncated: ranged anyway, flagged tcspc.truncated)")
    table, note = range_capture(cap, calib, out, estimator,
                                None if irf_ps is None else irf_ps * 1e-12, p_fa,
                                max_returns or (3 if spatial is None else 2), force=force,
                                spatial=spatial)
    if note:
        warn(note)
    _warn_chip(table)
    if not quiet:
        import polars as pl

        df = pl.from_arrow(table)
        more = df.filter(pl.col("detected") & (pl.col("return_index") > 0)).height
        df = df.filter(pl.col("return_index") == 0)
        det = df.filter(pl.col("detected"))
        err.print(f"{det.height} of {df.height} pixels detected"
                  + (f" (+{more} further returns)" if more else "")
                  + f" ({estimator}, P_fa {p_fa:g}) in "
                  f"{time.perf_counter() - t0:.2f} s; "
                  + instruments.detected_span(df.to_arrow())
                  + (f", median sigma {det['sigma_m'].median():.4f} m" if det.height else ""))
        err.print(f"wrote {out}")
    _warn_no_delay(calib)


def _not_for_instruments(fmt: str, **given) -> None:
    """Options of the thesis chip's path refused (not ignored) on an instrument's file."""
    used = [k.replace("_", "-") for k, v in given.items() if v]
    if used:
        raise click.UsageError(f"--{', --'.join(used)}: not for a {fmt} file")


def _warn_chip(table) -> None:
    """Say what the chip check found where the rows carry it (--force, a TDC alone)."""
    import json

    chk = json.loads((table.schema.metadata or {}).get(b"tcspc.chip_check", b"{}"))
    if chk.get("verdict") == "mismatch":
        warn(f"--force: the capture is not the calibration's chip ({chk['summary']}); "
             "every row flagged")
    elif chk.get("disagree"):
        warn(f"TDC(s) {chk['disagree']}: code-density pattern not the calibration's "
             "(their rows flagged)")


def _warn_no_delay(calib) -> None:
    """TDCs the calibration has no delay for are not ranged: say how many and why."""
    from collections import Counter

    why = Counter(r for r in calib.delay_reasons if r)
    if why:
        warn(f"{sum(why.values())} TDC(s) not ranged, no delay in the calibration: "
             + "; ".join(f"{n} {r}" for r, n in why.most_common()))


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
    "stage": ("pipeline.cli.stream", "stage",
              "Run one stage of the stream alone (the graph can span processes and hosts)."),
    "daemon": ("pipeline.cli.stream", "daemon",
               "Start the stream graph under a supervisor that restarts crashed stages."),
    "reconcile": ("pipeline.cli.stream", "reconcile",
                  "Finish or check a run offline: datasets against the journal, accounting."),
    "status": ("pipeline.cli.stream", "status",
               "Live view of a running daemon: per-stage health, rates, queues, restarts."),
    "calibrate": ("pipeline.cli.calibrate", "calibrate",
                  "Density test, LSB against light, and zero-distance delay."),
    "model": ("pipeline.cli.model", "model",
              "Chapter 2: link budget, ambient light, transmission, prediction, histograms."),
    "view": ("pipeline.cli.view", "view",
             "The live web page: daemon health, the sensor's histograms and maps, calibration."),
    "export": ("pipeline.cli.export", "export",
               "Ranges and a geometry as a point cloud (LAS, PLY, PCD, MCAP)."),
    "journal": ("pipeline.cli.journal", "journal",
                "The daemon's journal: a segment (any encoding) as the raw capture."),
}
#: Short help of the commands added by the layers above through the entry point.
_ENTRY_HELP = {"flow": "Run or serve the Prefect flows (calibration, sweeps, reports).",
               "demo": "The whole story on embedded defaults (what `make demo` runs)."}


def _register() -> None:
    for name, (module, attr, short) in _LAZY.items():
        cli.add_command(_Lazy(name, _module_command(module, attr), short), name)


def _register_entry_points() -> None:
    """Layers above the pipeline (the flows) add their commands through an entry point, so
    nothing here imports them (docs/design.md: nothing imports ``flows``). Read when a name is
    not a command of this module or the commands are listed: importlib.metadata and the
    scan cost 50-90 ms, which `tcspc histogram` does not pay."""
    if _Root.entry_points_read:
        return
    _Root.entry_points_read = True
    from importlib.metadata import entry_points

    for ep in entry_points(group="tcspc.commands"):
        if ep.name not in cli.commands:
            cli.add_command(_Lazy(ep.name, ep.load, _ENTRY_HELP.get(ep.name, ep.name)),
                            ep.name)


_register()


def main() -> None:
    """Entry point: project errors become one clear line and exit status 2."""
    try:
        _main()
    finally:
        # The interpreter's collections at exit scan every object of the ~360 modules a
        # command imports: 40-60 ms, a third of `tcspc --help`. Frozen, they are left to
        # the OS like the rest of the process's memory (atexit handlers still run).
        gc.freeze()


def _main() -> None:
    cli.main(prog_name="tcspc")


if __name__ == "__main__":
    main()
