"""Data-path throughput: decode, decode+filter, decode+filter+histogram, in words/s.

Prints a Markdown table with the command, the machine and the numbers, beside a plain-numpy
memory-bandwidth baseline measured in the same run (the ratio, not the absolute time, is the
figure), and tttrlib's micro-time histogram over the same number of events when tttrlib is
installed (``pip install -e '.[bench]'``). Everything runs pinned to one core.

    python benchmarks/datapath.py [--words 100e6] [--capture-gb 4] [--out results.md]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.io.capture import CaptureWriter  # noqa: E402
from schemas.constants import N_CLASSES  # noqa: E402
from stages.artifact import ArtifactBounds  # noqa: E402
from stages.codec import classify_words, decode_fields  # noqa: E402
from stages.datapath import WordTables, accumulate  # noqa: E402
from stages.testpattern import pattern_words  # noqa: E402

CHUNK = 1 << 20


def machine() -> str:
    cpu = platform.processor() or "?"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import numba

    pinned = len(os.sched_getaffinity(0))
    return (f"{cpu}, {os.cpu_count()} cores (this process may use {pinned}), "
            f"Python {platform.python_version()},"
            f" numpy {np.__version__}, numba {numba.__version__}")


def emit(lines: list[str], out: Path | None) -> None:
    """Print a benchmark's table, and keep it in ``out`` when asked."""
    text = "\n".join(lines)
    print(text)
    if out:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text + "\n")


def best_of(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def make_words(n_words: int, hit_prob: float, n_tdc: int = 128) -> tuple[np.ndarray, object]:
    """A realistic class mix, tiled from a 16 M-word block of whole cycles."""
    block, truth = pattern_words((1 << 24) // n_tdc, n_tdc, hit_prob=hit_prob,
                                 artifact_prob=1e-3, rng=1)
    reps = -(-n_words // block.size)
    return np.tile(block, reps), truth


def chunked(words, fn):
    for s in range(0, words.size, CHUNK):
        fn(words[s:s + CHUNK], s)


def run_memory(words):
    dst = np.empty_like(words)
    read = best_of(lambda: np.add.reduce(words, dtype=np.uint64), 3)
    copy = best_of(lambda: np.copyto(dst, words), 3)
    return [("memory: read (np.sum)", read), ("memory: read+write (np.copyto)", copy)]


def run_stages(words, truth, n_tdc=128, repeat=2):
    bounds = ArtifactBounds(truth.n_min, truth.n_max)
    rows = []

    def decode_only(w, s):
        f = decode_fields(w)
        f.d1st, f.d2nd  # noqa: B018 - the codes are part of decoding

    rows.append(("decode (numpy, fields + D1st/D2nd)", best_of(lambda: chunked(words,
                                                                             decode_only), 1)))

    def decode_filter(w, s):
        classify_words(w, n_tdc, s, bounds.n_min, bounds.n_max)

    rows.append(("decode + filter (numpy reference classifier)",
                 best_of(lambda: chunked(words, decode_filter), 1)))
    tables = WordTables(n_tdc, bounds)
    results = {}
    for engine in ("numpy", "numba"):
        hits = np.zeros((n_tdc, 512), np.uint64)
        cc = np.zeros((N_CLASSES, n_tdc), np.uint64)
        accumulate(words[:n_tdc * 8], 0, tables, hits, cc, engine)  # compile / build tables

        def fused(engine=engine, hits=hits, cc=cc):
            hits[:] = 0
            cc[:] = 0
            accumulate(words, 0, tables, hits, cc, engine)

        rows.append((f"decode + filter + histogram ({engine}, fused)", best_of(fused, repeat)))
        results[engine] = (hits.copy(), cc.copy())
    agree = all(np.array_equal(a, b) for a, b in zip(results["numpy"], results["numba"],
                                                     strict=True))
    return rows, agree


def run_tttrlib(n_events: int, truth_hits_codes):
    try:
        import tttrlib
    except ImportError:
        return None, "tttrlib not installed (pip install -e '.[bench]')"
    rng = np.random.default_rng(0)
    micro = truth_hits_codes[rng.integers(0, truth_hits_codes.size, n_events)].astype(np.uint16)
    macro = np.arange(n_events, dtype=np.uint64)
    chan = (np.arange(n_events) % 128).astype(np.int8)
    ev = np.zeros(n_events, np.int8)
    t0 = time.perf_counter()
    data = tttrlib.TTTR(macro, micro, chan, ev)
    build = time.perf_counter() - t0
    # minlength is required: without it the call dies with SIGFPE on array-built data.
    dt = best_of(lambda: data.get_microtime_histogram(micro_time_coarsening=1,
                                                      minlength=512), 2)
    return dt, f"tttrlib {tttrlib.__version__}; TTTR built from arrays in {build:.1f} s"


def run_capture(gb: float, workdir: Path) -> dict:
    """Write a capture of ``gb`` GB and histogram it in a fresh process; report peak RSS.

    Peak RSS is the child's VmHWM: ru_maxrss would carry over the parent's peak across
    fork+exec on Linux (the parent holds the 100 M-word arrays).
    """
    n_tdc = 128
    block, _ = pattern_words((1 << 22) // n_tdc, n_tdc, hit_prob=0.05, rng=2)
    n_blocks = max(1, int(gb * 1e9 / 4 / block.size))
    path = workdir / "big"
    with CaptureWriter(path, n_tdc, kind="range", note="benchmark") as w:
        for _ in range(n_blocks):
            w.write(block)
    code = ("import json, sys, time; sys.path.insert(0, %r);"
            "from pipeline.io.capture import Capture;"
            "from pipeline.offline.datapath import histogram_capture;"
            "cap = Capture(%r); t0 = time.perf_counter(); s, b = histogram_capture(cap);"
            "dt = time.perf_counter() - t0;"
            "print(json.dumps({'words': cap.n_words, 'seconds': dt, 'passes': 2,"
            "'maxrss_kib': int([l.split()[1] for l in open('/proc/self/status')"
            " if l.startswith('VmHWM')][0]),"
            "'total': int(s.class_counts.sum())}))")
    code = code % (str(Path(__file__).resolve().parents[1]), str(path))
    proc = subprocess.run(["taskset", "-c", "0", sys.executable, "-c", code],
                          capture_output=True, text=True, check=True)
    res = json.loads(proc.stdout)
    res["bytes"] = path.with_suffix(".bin").stat().st_size
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--words", type=float, default=100e6)
    ap.add_argument("--capture-gb", type=float, default=4.0,
                    help="size of the capture processed from disk (0 to skip)")
    ap.add_argument("--out", type=Path, default=None, help="also write the table here")
    args = ap.parse_args()
    os.sched_setaffinity(0, {0})
    n = int(args.words)
    lines = [f"command: `python {' '.join(sys.argv)}`", f"machine: {machine()}", ""]
    for label, hit_prob in (("photon-starving mix: 5% hits, 0.1% artifacts", 0.05),
                            ("density-test mix: 30% hits", 0.3)):
        words, truth = make_words(n, hit_prob)
        rows = run_memory(words) if hit_prob == 0.05 else []
        stage_rows, agree = run_stages(words, truth)
        rows += stage_rows
        base = rows[0][1] if hit_prob == 0.05 else base  # noqa: F821 - set on first mix
        lines += [f"### {label}, {words.size / 1e6:.0f} M words",
                  "", "| step | M words/s | time/baseline read |", "|---|---:|---:|"]
        for name, dt in rows:
            lines.append(f"| {name} | {words.size / dt / 1e6:,.0f} | {dt / base:.1f}x |")
        if hit_prob == 0.05:
            codes = np.flatnonzero(truth.hits.sum(axis=0))
            dt, note = run_tttrlib(words.size, np.repeat(codes, 1))
            if dt is not None:
                lines.append(f"| peer: tttrlib get_microtime_histogram, same number of events"
                             f" | {words.size / dt / 1e6:,.0f} | {dt / base:.1f}x |")
            lines.append(f"\n{note}")
        lines.append(f"\nnumba and numpy histograms and class counts identical: {agree}\n")
        del words
    if args.capture_gb > 0:
        with tempfile.TemporaryDirectory(dir=Path.cwd()) as d:
            r = run_capture(args.capture_gb, Path(d))
        lines += [f"### `tcspc histogram` path on a {r['bytes'] / 1e9:.2f} GB capture from disk",
                  "", f"{r['words'] / 1e6:,.0f} M words, two passes (bounds estimated, then "
                  f"histogram): {r['seconds']:.1f} s = "
                  f"{r['passes'] * r['words'] / r['seconds'] / 1e6:,.0f} M words/s per pass; "
                  f"peak RSS {r['maxrss_kib'] / 1024:,.0f} MiB; every word classed: "
                  f"{r['total'] == r['words']}", ""]
    emit(lines, args.out)


if __name__ == "__main__":
    main()
