"""How well could any estimator place the scene's edges? An oracle, written apart from
the estimator (numpy and scipy only, nothing of ``stages``), that knows more than any
estimator can: every plane's depth and slope, every edge's direction and where every
other edge lies. It does not know where one edge lies, within +- ``REACH`` pixels across
it. From the frame's photons (the exact Poisson likelihood of each pixel's whole
histogram, the pulse and the background as the generator made them) it takes the
posterior of that edge's place (a uniform prior over a grid of ``STEP`` pixels), and
reports for each pixel the depth, among the surfaces it may have, of the least expected
squared error (the RMSE's own decision: beside a pane, the wall behind, which is right
either way; beside the sky, the surface). One edge at a time, all the scene's edges
(``benchmarks.spatial_scenes.EDGES``); a pixel moved by two edges (a corner) is wrong
where either puts it wrong.

An estimator that does not know what the oracle knows, and reports for each pixel one
of the surfaces the pixel may have, can only do worse on average: the Bayes risk does
not grow as information grows. The bound is on the expected squared error, so the
column to read against a goal is the root of the mean MSE over the frames (the median
and the frames within it are shown too). Where it exceeds a goal, no such estimator
meets it on average (reporting a depth between two surfaces, or another plane carried
into the pixel, could; the spatial estimator must not invent a surface). The frames
are drawn at the scene's true edges; a corner pixel wrong under either of its edges
counts once, which makes the oracle's figure a little high there (no pixel of seeds
1-2 at 30 degrees was wrong under both, an outside review found). Where the oracle
places every pixel, the photons do not rule a goal out; that does not show an
estimator that reaches it.

    python benchmarks/spatial_oracle.py [--angles 0 30] [--seeds 1-25] [--cell 2,50]

prints, per angle, the oracle's pixels on the wrong surface a frame and its RMSE (the
label errors alone, and with a 1 cm error on every pixel, about what the spatial
estimator reaches on its right pixels), against the spatial estimator's own when
``--ours`` is given.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np
from scipy.special import ndtr

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from benchmarks.spatial_scenes import (  # noqa: E402
    BIN_S,
    EDGES,
    N_BINS,
    SIGMA_S,
    C,
    histograms,
    scene,
    window_errors,
)

REACH = 2.0   # pixels: the edge lies within this of its true place, the oracle knows
STEP = 0.01   # pixels: the grid of its places
FLOOR_M = 0.01  # the error assumed on every pixel beside the labels' (the estimator's)


def _configs(angle, h=64, w=64, names=None):
    """Per edge (``names``: these only; default all): the pixels a move within REACH
    changes, the moves (pixels across), and per move which of them it changes and their
    depth and share then."""
    truth = scene(h, w, angle)
    moves = np.arange(-REACH, REACH + STEP / 2, STEP)
    out = {}
    for name in names or EDGES:
        v = EDGES[name]
        unit = h if name.endswith(("_r", "_r0", "_r1")) else w
        alts = []
        for m in moves:
            sc = scene(h, w, angle, {name: v + m / unit})
            diff = ~(np.isclose(sc.depth, truth.depth, equal_nan=True).all(-1)
                     & np.isclose(sc.share, truth.share).all(-1))
            alts.append((diff, sc.depth, sc.share))
        touched = np.zeros((h, w), bool)
        for diff, _, _ in alts:
            touched |= diff
        idx = np.nonzero(touched.ravel())[0]
        if not idx.size:
            continue
        changed = np.stack([a[0].ravel()[idx] for a in alts])           # (moves, n)
        depth = np.stack([a[1].reshape(-1, 2)[idx] for a in alts])     # (moves, n, 2)
        share = np.stack([a[2].reshape(-1, 2)[idx] for a in alts])
        out[name] = (idx, moves, changed, depth, share)
    return truth, out


def _loglik(counts, depth, share, signal, background):
    """Each pixel's Poisson log-likelihood of its histogram (up to a constant):
    counts (n, bins), depth and share (n, 2) its surfaces (NaN: none)."""
    edges = np.arange(N_BINS + 1) * BIN_S
    lam = np.full(counts.shape, background / N_BINS)
    for k in range(2):
        tau = 2 * depth[:, k] / C
        ok = np.isfinite(tau)
        z = (edges[None, :] - np.where(ok, tau, 0.0)[:, None]) / SIGMA_S
        p = np.diff(ndtr(z), axis=1)
        lam += np.where(ok, signal * share[:, k], 0.0)[:, None] * p
    return (counts * np.log(lam)).sum(1) - lam.sum(1)


def oracle(angle, seed, signal, background, prepared=None):
    """The oracle's depth a pixel (NaN: none) and its pixels given a depth on no surface
    they have, for one frame."""
    truth, cfg = prepared or _configs(angle)
    h, w, _ = truth.depth.shape
    counts = histograms(truth, signal, background, seed).reshape(h * w, N_BINS)
    tdep, tsh = truth.depth.reshape(-1, 2), truth.share.reshape(-1, 2)
    report = truth.depth[..., 0].copy().ravel()
    report = np.where(np.isfinite(truth.depth.reshape(-1, 2)[:, 1]),
                      np.fmin(report, tdep[:, 1]), report)  # (the nearer, where two)
    wrong = np.zeros(h * w, bool)
    for idx, moves, changed, depth, share in cfg.values():
        c = counts[idx]
        ll0 = _loglik(c, tdep[idx], tsh[idx], signal, background)
        # each move's log-likelihood: the changed pixels' alternatives against the truth
        gain = np.zeros(moves.size)
        alt = {}  # (pixel, its surfaces then) -> its log-likelihood
        for i in range(moves.size):
            ch = np.nonzero(changed[i])[0]
            keys = [(j, depth[i, j].tobytes(), share[i, j].tobytes()) for j in ch]
            need = [n for n, k in enumerate(keys) if k not in alt]
            if need:
                js = ch[need]
                got = _loglik(c[js], depth[i, js], share[i, js], signal, background)
                alt.update(zip([keys[n] for n in need], got, strict=True))
            gain[i] = sum(alt[k] for k in keys) - ll0[ch].sum()
        post = np.exp(gain - gain.max())
        post /= post.sum()
        # each pixel: the posterior that it is not as the truth has it
        p_off = post @ changed
        for j in np.nonzero(p_off > 1e-9)[0]:
            # the depth it reports: of the surfaces it may have, the one of the least
            # expected squared error (a pixel with none, sky, costs nothing whatever it
            # reports; one of two surfaces, a pane's, nothing on either)
            who = np.nonzero(changed[:, j] & (post > 0))[0]
            configs = [tdep[idx[j]]] + [depth[i, j] for i in who]
            prob = np.concatenate([[1.0 - p_off[j]], post[who]])
            cand = np.unique(np.concatenate([x[np.isfinite(x)] for x in configs] + [[]]))
            if not cand.size:
                continue
            cost = np.zeros(cand.size)
            for x, pr in zip(configs, prob, strict=True):
                if np.isfinite(x).any():
                    cost += pr * np.nanmin(np.abs(cand[:, None] - x[None, :]), 1) ** 2
            d = cand[np.argmin(cost)]
            t = tdep[idx[j]]
            miss = np.nanmin(np.abs(d - t)) if np.isfinite(t).any() else 0.0
            if miss > 1e-9 and miss > (np.nanmin(np.abs(report[idx[j]] - t))
                                      if np.isfinite(report[idx[j]]) else -1.0):
                report[idx[j]] = d   # (moved by two edges: the worse of the two)
                wrong[idx[j]] = True
    return report.reshape(h, w), wrong.reshape(h, w), truth


def _rmse(truth, report):
    err = window_errors(truth, report)
    return float(np.sqrt(np.mean(err ** 2))), err


def _seeds(text):
    a, _, b = text.partition("-")
    return list(range(int(a), int(b) + 1)) if b else [int(x) for x in text.split(",")]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--angles", nargs="+", type=float, default=[0.0, 30.0])
    ap.add_argument("--seeds", default="1-25")
    ap.add_argument("--cell", default="2,50", help="signal,background photons a pixel")
    ap.add_argument("--ours", action="store_true", help="and the spatial estimator's")
    args = ap.parse_args(argv)
    signal, background = (float(x) for x in args.cell.split(","))
    seeds = _seeds(args.seeds)
    print(f"command: python benchmarks/{os.path.basename(__file__)} "
          + " ".join(argv if argv is not None else sys.argv[1:]))
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, python "
          f"{platform.python_version()}")
    print(f"cell ({signal:g}, {background:g}), seeds {args.seeds}, edge reach +-{REACH:g} px"
          f" in steps of {STEP:g}\n")
    head = ("| angle | oracle: wrong pixels a frame | > 10 cm | RMSE, labels only (median"
            " [range]) | with 1 cm a pixel | frames <= 3 cm | root of the mean MSE |")
    if args.ours:
        from stages.ranging.spatial import spatial
        head += (" spatial: > 10 cm a frame | its RMSE (median [range]) | frames <= 3 cm |"
                 " root of the mean MSE |")
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    for angle in args.angles:
        t0 = time.perf_counter()
        prepared = _configs(angle)
        n_wrong, n_off, rm, rm1, ours_off, ours_rm = [], [], [], [], [], []
        for s in seeds:
            report, wrong, truth = oracle(angle, s, signal, background, prepared)
            r, err = _rmse(truth, report)
            n_wrong.append(int(wrong.sum()))
            n_off.append(int((err > 0.1).sum()))
            rm.append(r)
            rm1.append(float(np.sqrt(r ** 2 + FLOOR_M ** 2)))
            if args.ours:
                counts = histograms(truth, signal, background, s)
                est = spatial(counts, BIN_S, SIGMA_S, 1e-3, threads=2)
                r2, err2 = _rmse(truth, est.t_s[..., 0] * C / 2)
                ours_off.append(int((err2 > 0.1).sum()))
                ours_rm.append(r2)
        row = (f"| {angle:g} | {np.mean(n_wrong):.2f} | {np.mean(n_off):.2f} | "
               f"{np.median(rm):.3f} [{min(rm):.3f}-{max(rm):.3f}] | {np.median(rm1):.3f} | "
               f"{sum(x <= 0.03 for x in rm1)}/{len(seeds)} | "
               f"{np.sqrt(np.mean(np.square(rm1))):.3f} |")
        if args.ours:
            row += (f" {np.mean(ours_off):.2f} | {np.median(ours_rm):.3f} "
                    f"[{min(ours_rm):.3f}-{max(ours_rm):.3f}] | "
                    f"{sum(x <= 0.03 for x in ours_rm)}/{len(seeds)} | "
                    f"{np.sqrt(np.mean(np.square(ours_rm))):.3f} |")
        print(row, flush=True)
        print(f"  ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)


if __name__ == "__main__":
    main()
