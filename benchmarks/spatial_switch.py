"""A step of the spatial estimator on and off (or a constant at an earlier value), over
the grid's frames (benchmarks/spatial_scenes.py, the goal's scene): per block of seeds,
the pixels more than 10 cm and more than 0.5 m off, the frames whose depth RMSE over the
surface pixels is within 3 cm, the root of the frames' mean MSE, and the pixels > 10 cm off that the
step fixed and made. The same frames, the same code but the switch.

    python benchmarks/spatial_switch.py --switch LINE_SKY [--seeds 1-125] [--block 25]
        [--angle 0] [--cell 2,50]
    python benchmarks/spatial_switch.py --was "LINE_PASSES=1"

``--switch`` names a boolean of stages/ranging/spatial.py (or edgelines.NAME,
planecut.NAME); "on" is the code as shipped, "off" the switch flipped. ``--was
NAME=VALUE`` sets a constant there to another value instead (a Python expression, numpy
as ``np``: the value it had before a change), against it as shipped.
"""

from __future__ import annotations

import argparse
import importlib
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks import spatial_scenes as gen  # noqa: E402
from stages.ranging.spatial import spatial  # noqa: E402


def _target(name: str, boolean: bool = True):
    mod, _, attr = name.rpartition(".")
    module = importlib.import_module(f"stages.ranging.{mod or 'spatial'}")
    if not hasattr(module, attr):
        raise SystemExit(f"{name}: no constant of stages.ranging.{mod or 'spatial'}")
    if boolean and not isinstance(getattr(module, attr), bool):
        raise SystemExit(f"{name}: no boolean switch of stages.ranging.{mod or 'spatial'}")
    return module, attr


def errors(sc, counts) -> np.ndarray:
    """Each surface pixel's error (m) of the first return, as every spatial figure."""
    est = spatial(counts, gen.BIN_S, gen.SIGMA_S, 1e-3, threads=2)
    return gen.window_errors(sc, est.t_s[..., 0] * gen.C / 2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    how = ap.add_mutually_exclusive_group(required=True)
    how.add_argument("--switch", help="a boolean step, flipped")
    how.add_argument("--was", help="NAME=VALUE: a constant at another value")
    ap.add_argument("--seeds", default="1-125")
    ap.add_argument("--block", type=int, default=25)
    ap.add_argument("--angle", type=float, default=0.0)
    ap.add_argument("--cell", default="2,50", help="signal,background photons a pixel")
    a = ap.parse_args()
    if a.switch is not None:
        module, attr = _target(a.switch)
        shipped = getattr(module, attr)
        other, what = not shipped, f"--switch {a.switch}"
    else:
        name, eq, expr = a.was.partition("=")
        if not eq:
            raise SystemExit(f"--was {a.was!r}: NAME=VALUE")
        module, attr = _target(name.strip(), boolean=False)
        shipped = getattr(module, attr)
        other, what = eval(expr, {"np": np}), f'--was "{a.was}"'   # (the user's own value)
    lo, _, hi = a.seeds.partition("-")
    seeds = list(range(int(lo), int(hi or lo) + 1))
    sig, bg = (float(x) for x in a.cell.split(","))
    sc = gen.scene(angle_deg=a.angle)
    where = np.argwhere(sc.surface)
    print(f"command: python benchmarks/spatial_switch.py {what} --seeds "
          f"{a.seeds} --block {a.block} --angle {a.angle:g} --cell {a.cell}")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, python "
          f"{platform.python_version()}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    print(f"{a.switch}: flipped -> as shipped ({shipped})\n" if a.switch is not None else
          f"{a.was} -> as shipped\n")
    print("| seeds | > 10 cm off | > 0.5 m off | frames within 3 cm | root of the mean MSE m "
          "| fixed | made |")
    print("|---|---:|---:|---:|---:|---|---|")
    for b in range(0, len(seeds), a.block):
        part = seeds[b:b + a.block]
        st = {k: [0, 0, 0, 0.0] for k in ("on", "off")}
        fixed, made = [], []
        for s in part:
            counts = gen.histograms(sc, sig, bg, s)
            e = {}
            for k, val in (("on", shipped), ("off", other)):
                setattr(module, attr, val)
                try:
                    e[k] = errors(sc, counts)
                finally:
                    setattr(module, attr, shipped)
                mse = float(np.mean(e[k] ** 2))
                st[k][0] += int((e[k] > 0.1).sum())
                st[k][1] += int((e[k] > 0.5).sum())
                st[k][2] += int(mse <= 0.03 ** 2)
                st[k][3] += mse
            fixed += [(s, *map(int, where[i])) for i in np.nonzero((e["off"] > 0.1)
                                                                  & (e["on"] <= 0.1))[0]]
            made += [(s, *map(int, where[i])) for i in np.nonzero((e["on"] > 0.1)
                                                                 & (e["off"] <= 0.1))[0]]
        n = len(part)

        rm = f"{np.sqrt(st['off'][3] / n):.4f} -> {np.sqrt(st['on'][3] / n):.4f}"
        fx = " ".join(f"{s}:({r},{c})" for s, r, c in fixed) or "-"
        mk = " ".join(f"{s}:({r},{c})" for s, r, c in made) or "-"
        cell = [f"{st['off'][i]} -> {st['on'][i]}" for i in range(3)]
        print(f"| {part[0]}-{part[-1]} | {cell[0]} | {cell[1]} | {cell[2]} of {n} | {rm} "
              f"| {fx} | {mk} |", flush=True)
    print("\n(each cell: flipped (or the earlier value) -> as shipped; fixed and made by "
          "the code as shipped: seed:(row,col) of pixels > 10 cm off)")


if __name__ == "__main__":
    main()
