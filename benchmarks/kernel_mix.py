"""The numba engine's calibrated loop against the hit fraction, beside the loop of an
earlier revision (the one-pass loop before the two passes of ``stages/datapath.py``).

Each fraction is ``stages.testpattern.pattern_words`` (128 TDCs, 80 000 cycles, 0.1 %
artifacts, hits at random codes), counted by numba's dispatcher on one thread (best of 4,
after a compile); both loops' histograms and class counts must be identical.

    python benchmarks/kernel_mix.py [--against 3ea4f9d] [--out results.md]
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.datapath import emit, machine  # noqa: E402
from schemas.constants import N_CLASSES  # noqa: E402
from stages import datapath as new  # noqa: E402
from stages.codec import PHASE_DECODE  # noqa: E402
from stages.testpattern import pattern_words  # noqa: E402

N_TDC = 128


def earlier_loop(rev: str):
    """``_kernel_loop`` of ``stages/datapath.py`` at ``rev``, compiled by numba."""
    import numba

    src = subprocess.run(["git", "show", f"{rev}:stages/datapath.py"], cwd=ROOT, check=True,
                         capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / "earlier_datapath.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("earlier_datapath", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return numba.njit(nogil=True)(mod._kernel_loop)


def best_rate(run, words, repeat=4):
    best, out = float("inf"), None
    for _ in range(repeat):
        hits = np.zeros((N_TDC, 512), np.uint64)
        cc = np.zeros((N_CLASSES, N_TDC), np.uint64)
        t0 = time.perf_counter()
        run(hits, cc)
        best = min(best, time.perf_counter() - t0)
        out = (hits, cc)
    return words.size / best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", default="3ea4f9d")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    old = earlier_loop(args.against)
    now = new._numba_loop("kernel", nogil=True)
    inblock = np.zeros((N_TDC, 256), np.bool_)
    inblock[:, 20:200] = True
    none = np.zeros((1, 1), np.uint64)
    lines = ["### the calibrated loop against the hit fraction", "",
             f"command: `python benchmarks/kernel_mix.py --against {args.against}`",
             f"machine: {machine()}; one thread, numba's dispatcher", "",
             f"| hits per word | {args.against}: one pass, M words/s | now: two passes, "
             "M words/s | now / before | identical |", "|---:|---:|---:|---:|---|"]
    for hp in (0.05, 0.18, 0.3, 0.5, 0.7, 0.9):
        words, _ = pattern_words(80_000, N_TDC, hit_prob=hp, artifact_prob=0.001, rng=1)
        words = np.ascontiguousarray(words, np.uint32)
        r_old, a = best_rate(lambda h, c, w=words: old(w, 0, N_TDC, PHASE_DECODE, inblock, h,
                                                       c, False, 0, none, False), words)
        r_new, b = best_rate(lambda h, c, w=words: now(w, 0, N_TDC, PHASE_DECODE, inblock, h,
                                                       c, False, 0, none, False,
                                                       new._scratch()), words)
        same = all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
        lines.append(f"| {hp:.2f} | {r_old / 1e6:.0f} | {r_new / 1e6:.0f} | "
                     f"{r_new / r_old:.2f}x | {same} |")
    emit(lines, args.out)


if __name__ == "__main__":
    main()
