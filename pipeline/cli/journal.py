"""``tcspc journal``: a daemon's journal segments as raw captures (loaded when named)."""

from __future__ import annotations

from pathlib import Path

import click


@click.group()
def journal() -> None:
    """The daemon's journal (STATE/journal): its segments as raw captures."""


@journal.command("export")
@click.argument("segment", type=click.Path(exists=True, dir_okay=False))
@click.argument("out", type=click.Path())
@click.option("--overwrite", is_flag=True, help="Replace an existing capture OUT.")
def export(segment: str, out: str, overwrite: bool) -> None:
    """Write a closed journal SEGMENT (RUN-000000.bin.nhz, .bin.zst or .bin, with its
    sidecar RUN-000000.json beside it) as the raw capture OUT (OUT.bin and OUT.json): the
    words byte for byte as they came in, whatever the segment's encoding. What `zstd -d`
    gives for a zstd segment, for a zstd-nohit one too. An existing OUT is replaced only
    with --overwrite."""
    from pipeline.io.atomic import check_output
    from pipeline.io.capture import Capture, CaptureWriter, capture_paths

    cap = Capture(segment)
    bin_path, _ = capture_paths(out)
    check_output(out, "capture", overwrite=overwrite, option="OUT",
                 expected_bytes=4 * cap.n_words)
    m = cap.meta
    with CaptureWriter(out, m.n_tdc, m.window_ns, m.t_laser_win_ns, kind=m.kind,
                       note=m.note, truth=m.truth) as w:
        for _, words in cap.iter_chunks():
            w.write(words)
    click.echo(f"{bin_path}: {w.n_words:,} words ({w.n_words // m.n_tdc:,} cycles of "
               f"{m.n_tdc} TDCs) from {Path(segment).name}")
