"""PicoQuant PTU readers: records/s of this project's reader against ptufile and tttrlib.

On the two shared files and on the HydraHarp V2 T3 file's records tiled to ~50 M records
(a synthetic PTU written with ``write_ptu``), each reader runs in a fresh process pinned
to one core (so its peak RSS, VmHWM, is its own), reading from the page cache. The
micro-time histograms and per-channel photon counts of the three readers are compared.
Then ``histogram_t3`` streams a ~4 GB synthetic file in a fresh process to show its
memory bound. Peers: ``pip install ptufile tttrlib``.

    python benchmarks/ptu.py [--records 50e6] [--big-gb 4] [--out benchmarks/results/ptu.md]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.datapath import emit, machine  # noqa: E402
from pipeline.io.ptu import histogram_t3, read_header, write_ptu  # noqa: E402

DATA = ROOT / "tests" / "data" / "picoquant"  # the public files of tests/data/README.md
SHARED = [DATA / "hydraharp_v20_t3.ptu", DATA / "picoharp_v30_t2.ptu"]
#: reader -> (label, applies to T2 files too)
READERS = {
    "ours-hist-numba": ("this reader: `histogram_t3` (numba)", False),
    "ours-hist-numpy": ("this reader: `histogram_t3` (numpy engine)", False),
    "ours-decode-numba": ("this reader: `iter_decoded_batches` -> Arrow (numba)", True),
    "ours-decode-numpy": ("this reader: `iter_decoded_batches` -> Arrow (numpy engine)", True),
    "ptufile-hist": ("ptufile: `decode_histogram`", False),
    "ptufile-decode": ("ptufile: `decode_records` (whole file)", True),
    "tttrlib-load": ("tttrlib: `TTTR(path)` (decodes the whole file)", True),
    "tttrlib-hist": ("tttrlib: `TTTR(path)` + `get_microtime_histogram`", False),
}


def vmhwm_kib() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM"):
            return int(line.split()[1])
    return -1


def by_channel_dtime(channel, dtime, n_channels, header) -> np.ndarray:
    n_bins = header.format.n_dtime_codes
    key = channel.astype(np.int64) * n_bins + dtime.astype(np.int64)
    return np.bincount(key, minlength=n_channels * n_bins).reshape(
        n_channels, n_bins).astype(np.uint64)


def child(reader: str, path: str, out: str, repeat: int) -> None:
    """One reader in this fresh process: best-of-``repeat`` seconds, peak RSS, and what it
    found (per-channel photons and, for T3, the histogram by channel) saved to ``out``."""
    os.sched_setaffinity(0, {0})
    header = read_header(path)
    t3 = header.format.is_t3
    result: dict = {}

    def run():
        if reader.startswith("ours-hist"):
            counts, _, tally, _ = histogram_t3(path, engine=reader.rsplit("-", 1)[1])
            result.update(hist=counts, n_photons=tally.n_photons)
        elif reader.startswith("ours-decode"):
            from pipeline.io.ptu import DecodeReport, iter_decoded_batches

            report = DecodeReport()
            for _ in iter_decoded_batches(path, report=report,
                                          engine=reader.rsplit("-", 1)[1]):
                pass
            result.update(n_photons=report.n_photons, n_sync=report.n_sync)
        elif reader == "ptufile-hist":
            import ptufile

            with ptufile.PtuFile(path) as f:
                # dtime: every code (the default, the bins of one sync period, would drop
                # the photons beyond it)
                result.update(hist=f.decode_histogram(dtype=np.uint64,
                                                      dtime=header.format.n_dtime_codes))
        elif reader == "ptufile-decode":
            import ptufile

            with ptufile.PtuFile(path) as f:
                result.update(records=f.decode_records())
        else:
            import tttrlib

            data = tttrlib.TTTR(path, "PTU")
            if reader == "tttrlib-hist":
                # minlength: tttrlib's default (the header's 512 channels) drops photons
                result.update(hist1=data.get_microtime_histogram(
                    micro_time_coarsening=1, minlength=header.format.n_dtime_codes)[0])
            result.update(data=data)

    if reader.startswith("ours"):  # load the compiled kernels before the clock starts
        from stages.instruments.ptu import decode_records, histogram_records

        engine = reader.rsplit("-", 1)[1]
        few = np.zeros(8, np.uint32)
        decode_records(few, header.format, engine=engine)
        if t3:
            histogram_records(few, header.format, np.zeros((1, 1), np.uint64), engine=engine)
    times = []
    for _ in range(repeat):
        result.clear()
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    peak = vmhwm_kib()  # before the checks below allocate their own
    found: dict = {}
    # what the reader found, compared across readers by the parent (not timed)
    if "records" in result:
        r = result["records"]
        ph = r["channel"] >= 0
        found["per_channel"] = np.bincount(r["channel"][ph].astype(np.int64)).tolist()
        if t3:
            result["hist"] = by_channel_dtime(r["channel"][ph], r["dtime"][ph],
                                              len(found["per_channel"]), header)
    if "data" in result:
        d = result["data"]
        ph = np.asarray(d.get_event_type()) == 0
        ch = np.asarray(d.get_routing_channel())[ph].astype(np.int64)
        found["per_channel"] = np.bincount(ch).tolist()
        if t3 and reader == "tttrlib-hist":
            hist = by_channel_dtime(ch, np.asarray(d.get_micro_times())[ph],
                                    len(found["per_channel"]), header)
            result["hist"] = hist
            found["tttrlib_hist_equals_sum"] = bool(np.array_equal(
                np.asarray(result["hist1"], np.float64), hist.sum(axis=0)))
    if "hist" in result:
        hist = np.asarray(result["hist"], np.uint64)
        found["per_channel"] = hist.sum(axis=1).tolist()
        np.save(out, hist)
    if "n_photons" in result:
        found["n_photons"] = result["n_photons"]
    if reader.startswith("ours-decode"):  # per channel in the peers' numbering
        from pipeline.io.ptu import decode
        from stages.instruments.ptu import SYNC_CHANNEL

        t = decode(path)
        ch = t.column("channel").to_numpy()[t.column("kind").to_numpy() == 0].astype(int)
        if header.format.layout == "picoharp" and not t3:  # sync = 0, input k = k + 1
            ch = np.where(ch == SYNC_CHANNEL, 0, ch + 1)
        if t3 or header.format.layout == "picoharp":
            found["per_channel"] = np.bincount(ch).tolist()
    print(json.dumps({"seconds": min(times), "vmhwm_kib": peak, **found}))


def measure(reader: str, path: Path, work: Path, repeat: int) -> dict | None:
    out = work / f"{reader}-{path.stem}.npy"
    proc = subprocess.run([sys.executable, __file__, "--child", reader, str(path), str(out),
                           str(repeat)], capture_output=True, text=True)
    if proc.returncode:
        err = (proc.stderr.strip().splitlines() or ["?"])[-1]
        return {"error": err[:200]}
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    res["hist_path"] = str(out) if out.exists() else None
    return res


def peer_versions() -> str:
    out = []
    for name in ("ptufile", "tttrlib"):
        try:
            mod = __import__(name)
            out.append(f"{name} {mod.__version__}")
        except ImportError:
            out.append(f"{name} not installed")
    return ", ".join(out)


def table_for(path: Path, work: Path, repeat: int, rounds: int) -> list[str]:
    h = read_header(path)
    n = h.n_readable
    lines = [f"### {path.name}: {h.format.name}, {n / 1e6:,.2f} M records, "
             f"{h.file_bytes / 1e6:,.1f} MB", "",
             "| reader | M records/s | seconds | peak RSS (MiB) |", "|---|---:|---:|---:|"]
    results: dict[str, dict] = {}
    readers = [k for k, (_, any_mode) in READERS.items() if h.format.is_t3 or any_mode]
    # rounds interleave the readers, so a change in the machine's other load does not
    # favour the reader that happened to run when the machine was quiet
    for _ in range(rounds):
        for reader in readers:
            r = measure(reader, path, work, repeat)
            best = results.get(reader)
            if best is None or ("error" not in r and r["seconds"] < best.get("seconds", 1e30)):
                results[reader] = r
    for reader in readers:
        label, r = READERS[reader][0], results[reader]
        if "error" in r:
            lines.append(f"| {label} | failed: {r['error']} | | |")
            continue
        lines.append(f"| {label} | {n / r['seconds'] / 1e6:,.1f} | {r['seconds']:.3f} | "
                     f"{r['vmhwm_kib'] / 1024:,.0f} |")
    # agreement: per-channel photon counts of every reader; histograms of the T3 readers
    per = {k: tuple(np.trim_zeros(np.array(v["per_channel"]), "b").tolist())
           for k, v in results.items() if "per_channel" in v}
    counts = {k: v.get("n_photons") for k, v in results.items() if "n_photons" in v}
    lines.append("")
    lines.append(f"photons per channel: {sorted(set(per.values()))} "
                 f"(readers agree: {len(set(per.values())) == 1}); our photon totals "
                 f"{sorted(set(counts.values()))}")
    hists = {k: np.load(v["hist_path"]) for k, v in results.items()
             if v.get("hist_path")}
    if hists:
        ref = hists.get("ours-hist-numba")
        same = {}
        for k, hist in hists.items():
            rows, bins = min(hist.shape[0], ref.shape[0]), min(hist.shape[1], ref.shape[1])
            same[k] = bool(np.array_equal(hist[:rows, :bins], ref[:rows, :bins])
                           and hist.sum() == ref.sum())
        lines.append(f"histograms identical to ours (channel x dtime, every photon): {same}")
        tt = results.get("tttrlib-hist", {}).get("tttrlib_hist_equals_sum")
        if tt is not None:
            lines.append(f"tttrlib's get_microtime_histogram (all channels, minlength = "
                         f"{h.format.n_dtime_codes}) equals the summed histogram: {tt}")
    lines.append("")
    return lines


def tile(src: Path, dst: Path, n_records: float) -> Path:
    """The records of ``src`` repeated to ~``n_records`` (overflows included, so times keep
    increasing), written in bounded memory."""
    h = read_header(src)
    block = np.fromfile(src, "<u4", count=h.n_readable, offset=h.data_offset)
    reps = max(1, int(round(n_records / block.size)))
    tags = {k: v for k, v in h.tags.items()  # the source's, but for the record count
            if k not in ("TTResult_NumberOfRecords", "Header_End")}
    return write_ptu(dst, h.record_type, (block for _ in range(reps)), tags=tags)


def big_file_rss(gb: float, work: Path) -> list[str]:
    src = SHARED[0]
    path = tile(src, work / "big.ptu", gb * 1e9 / 4)
    try:
        h = read_header(path)
        r = measure("ours-hist-numba", path, work, 1)
        if "error" in r:
            raise RuntimeError(r["error"])
        in_hist = int(np.load(r["hist_path"]).sum())
        r["records"], size = h.n_readable, path.stat().st_size
    finally:
        path.unlink(missing_ok=True)
    return [f"### `histogram_t3` on a {size / 1e9:.2f} GB file ({r['records'] / 1e6:,.0f} M "
            "records), fresh process", "",
            f"{r['seconds']:.1f} s = {r['records'] / r['seconds'] / 1e6:,.0f} M records/s "
            f"(page cache cold or warm, as the OS has it); peak RSS (VmHWM) "
            f"{r['vmhwm_kib'] / 1024:,.0f} MiB (< 1 GiB: {r['vmhwm_kib'] < 1 << 20}); every "
            f"record read and every photon in the histogram: {r['n_photons'] == in_hist} "
            f"({in_hist:,} photons); file deleted afterwards", ""]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--records", type=float, default=50e6,
                    help="records of the tiled HydraHarp T3 file")
    ap.add_argument("--big-gb", type=float, default=4.0,
                    help="size of the file for the memory bound (0 to skip)")
    ap.add_argument("--rounds", type=int, default=5,
                    help="rounds over all readers; each reader's best round is kept")
    ap.add_argument("--out", type=Path, default=None, help="also write the table here")
    ap.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        reader, path, out, repeat = args.child
        child(reader, path, out, int(repeat))
        return
    lines = [f"command: `python {' '.join(sys.argv)}`", f"machine: {machine()}",
             f"peers: {peer_versions()}", "",
             "Each reader in a fresh process pinned to one core, files in the page cache; "
             f"{args.rounds} rounds over all readers, each reader's best kept (a round runs "
             "it once on the tiled file, 5 times on a shared file). M records/s counts every "
             "record of the file (photons, overflows, markers). Peak RSS includes the "
             "interpreter and its imports: every process reads the header with this "
             "project's reader, so numba and pyarrow are loaded (~210 MiB; ~256 MiB with our "
             "kernels loaded).", ""]
    with tempfile.TemporaryDirectory(dir=Path.cwd()) as d:
        work = Path(d)
        tiled = tile(SHARED[0], work / "tiled.ptu", args.records)
        lines += table_for(tiled, work, 1, args.rounds)
        tiled.unlink()
        for path in SHARED:
            lines += table_for(path, work, 5, args.rounds)
        if args.big_gb > 0:
            lines += big_file_rss(args.big_gb, work)
    load = os.getloadavg()
    lines.insert(3, f"load average at the end (1/5/15 min): {load[0]:.1f} / {load[1]:.1f} / "
                    f"{load[2]:.1f} on {os.cpu_count()} cores (other work on the machine "
                    "slows every reader alike)")
    emit(lines, args.out)


if __name__ == "__main__":
    main()
