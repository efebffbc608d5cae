"""The spatial estimator on scenes it was not tuned on (:mod:`benchmarks.probe_scenes`):
what docs/ranging.md claims for it (2 sigma covers about 95 % of the errors, detected
and undetected; false surfaces; no ramp at edges; no invented surface), scored per scene
and cell, pooled over seeds.

    python benchmarks/spatial_probe.py run GROUP [--out DIR]   # appends DIR/GROUP.jsonl
                                    # (report: a frame run again, its latest record)
    python benchmarks/spatial_probe.py report [--out DIR] [GROUP ...]

Groups: main (12 scenes x 4 cells x 3 seeds), sky (all-sky frames: every detection a
false alarm, p_fa 1e-3 and 1e-2), bgshape (backgrounds rising 3x or falling as e^-3t),
pulse (the true pulse 1.3x and 0.77x the sigma given), shape (48 x 80 and 16 x 16),
mixed (each photon at a random point of its pixel), fov (the flat wall at 20 and 10
degrees), texture (the signal's reflectance a 7x checker or a 9x ramp across the
frame, and flat on the same seeds). The tables are in
benchmarks/results/spatial_probe.md.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import sys
import time
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks import probe_scenes as gen  # noqa: E402
from stages.ranging.spatial import spatial  # noqa: E402

C = gen.C
CELLS = [(10, 2), (5, 10), (2, 10), (2, 50)]


def nbhd(a, k=1):
    """(h, w, n) -> (h, w, n * (2k+1)^2) values of the 3x3 neighbourhood (NaN-padded)."""
    h, w, n = a.shape
    p = np.full((h + 2 * k, w + 2 * k, n), np.nan)
    p[k:k + h, k:k + w] = a
    out = [p[k + dr:k + dr + h, k + dc:k + dc + w] for dr in range(-k, k + 1)
           for dc in range(-k, k + 1)]
    return np.concatenate(out, -1)


def score(est, tr, elapsed, wlist):
    t = est.t_s
    sg = est.sigma_s
    det = est.detected
    d = C * t / 2
    s = C * sg / 2
    surf = np.isfinite(tr).any(-1)
    empty = ~surf
    with np.errstate(invalid="ignore"):
        e_all = np.abs(d[..., :, None] - tr[..., None, :])          # (h, w, R, ss)
        err = np.nanmin(np.where(np.isfinite(e_all), e_all, np.inf), -1)  # (h, w, R)
    err[~np.isfinite(d)] = np.inf
    e0, s0, d0 = err[..., 0], s[..., 0], det[..., 0]
    fin0 = np.isfinite(d[..., 0])
    m = surf & fin0
    out = dict(
        n_surf=int(surf.sum()), n_empty=int(empty.sum()),
        n_surf_nan=int((surf & ~fin0).sum()),
        rmse=float(np.sqrt(np.mean(e0[m] ** 2))) if m.any() else None,
        rmse_det=float(np.sqrt(np.mean(e0[surf & d0] ** 2))) if (surf & d0).any() else None,
        off10=int((surf & (e0 > 0.1)).sum()),
        n_det=int((surf & d0).sum()),
        cov_det=int((surf & d0 & (e0 <= 2 * s0)).sum()),
        n_und=int((surf & ~d0 & fin0).sum()),
        cov_und=int((surf & ~d0 & fin0 & (e0 <= 2 * s0)).sum()),
        # detected (first) pixels > 10 cm off, and how many of those are covered by 2 sigma
        det_off10=int((surf & d0 & (e0 > 0.1)).sum()),
        und_off10=int((surf & ~d0 & (e0 > 0.1)).sum()),
        false_surf=int((empty & det.any(-1)).sum()),
        false_surf_own=int((empty & (det & est.own).any(-1)).sum()),
        false_surf_sur=int((empty & (det & est.surrounded).any(-1)).sum()),
        elapsed=elapsed, warnings=wlist,
    )
    # invented surfaces: detected returns (any index) on surface pixels > max(10 cm, 3 sigma)
    # from every true range in the pixel's 3x3 neighbourhood
    nb = nbhd(tr)
    with np.errstate(invalid="ignore"):
        en = np.abs(d[..., :, None] - nb[..., None, :])
        en = np.nanmin(np.where(np.isfinite(en), en, np.inf), -1)
    inv = det & surf[..., None] & (en > np.maximum(0.1, 3 * s))
    out["invented_r0"] = int(inv[..., 0].sum())
    out["invented_r1"] = int(inv[..., 1:].sum())
    out["det_r1_surf"] = int((det[..., 1:] & surf[..., None]).sum())
    # ramp: pixels at a depth edge (3x3 true range spread > 0.3 m), detected first return
    # strictly between the neighbourhood's min and max and > 3 sigma from every true range
    lo, hi = np.nanmin(np.where(np.isfinite(nb), nb, np.inf), -1), np.nanmax(
        np.where(np.isfinite(nb), nb, -np.inf), -1)
    edge = surf & (hi - lo > 0.3) & np.isfinite(hi) & np.isfinite(lo)
    with np.errstate(invalid="ignore"):
        ramp = edge & d0 & (d[..., 0] > lo) & (d[..., 0] < hi) & (en[..., 0] > 3 * s0)
        ramp_und = edge & ~d0 & fin0 & (d[..., 0] > lo) & (d[..., 0] < hi) & (en[..., 0] > 3 * s0)
    out["n_edge_det"] = int((edge & d0).sum())
    out["ramp"] = int(ramp.sum())
    out["ramp_und"] = int(ramp_und.sum())
    with np.errstate(invalid="ignore"):
        ramp10 = ramp & (en[..., 0] > 0.1)
    out["ramp10"] = int(ramp10.sum())
    out["ramp_max_m"] = float(np.max(en[..., 0][ramp])) if ramp.any() else 0.0
    # sanity
    out["nan_det"] = int((det & ~np.isfinite(t)).sum())
    out["bad_sigma"] = int((np.isfinite(t) & ~(np.isfinite(sg) & (sg > 0))).sum())
    out["det_not_finite_t"] = int((det & ~np.isfinite(t)).sum())
    # worst undercovered detected pixels (z = err / sigma)
    z = np.where(surf & d0, e0 / s0, 0)
    if (surf & d0).any():
        out["z_det_p99"] = float(np.percentile(z[surf & d0], 99))
        out["z_det_max"] = float(z.max())
    return out


def run(scene, h, w, sig, bg, seed, p_fa=1e-3, ss=1, pulse_mult=1.0, bgk="flat",
        threads=2, keep=None, refl="flat"):
    counts, tr = gen.histograms(gen.SCENES[scene], h, w, sig, bg, seed, ss=ss,
                                pulse_sigma_s=gen.SIGMA_S * pulse_mult, bg=bgk, refl=refl)
    with warnings.catch_warnings(record=True) as wl:
        warnings.simplefilter("always")
        t0 = time.perf_counter()
        try:
            est = spatial(counts, gen.BIN_S, gen.SIGMA_S, p_fa, threads=threads)
        except Exception as ex:  # noqa: BLE001
            return dict(scene=scene, h=h, w=w, sig=sig, bg=bg, seed=seed, p_fa=p_fa, ss=ss,
                        pulse_mult=pulse_mult, bgk=bgk, refl=refl, crash=repr(ex))
        el = time.perf_counter() - t0
    r = score(est, tr, el, sorted({str(x.message)[:120] for x in wl}))
    if keep:  # the estimates, for a closer look
        os.makedirs(keep, exist_ok=True)
        np.savez_compressed(
            f"{keep}/{scene}_{h}x{w}_{sig}_{bg}_{seed}_{p_fa:g}_{ss}_{pulse_mult}_{bgk}"
            f"_{refl}.npz",
            t_s=est.t_s, sigma_s=est.sigma_s, detected=est.detected, own=est.own,
            surrounded=est.surrounded)
    r.update(scene=scene, h=h, w=w, sig=sig, bg=bg, seed=seed, p_fa=p_fa, ss=ss,
             pulse_mult=pulse_mult, bgk=bgk, refl=refl)
    return r


def jobs(group):
    seeds = [1, 2, 3]
    if group == "main":
        for sc in ["sphere", "flatwall", "cylinder", "steep10cm", "steep_diag", "grazing", "fence",
                   "wire", "edge12", "edge45", "triangle", "mostly_sky"]:
            for sig, bg in CELLS:
                for s in seeds:
                    yield dict(scene=sc, h=64, w=64, sig=sig, bg=bg, seed=s)
    elif group == "sky":
        for p_fa in (1e-3, 1e-2):
            for bg in (2, 10, 50):
                for s in range(1, 9):
                    yield dict(scene="sky", h=64, w=64, sig=0, bg=bg, seed=100 + s,
                               p_fa=p_fa)
    elif group == "bgshape":
        for bgk in ("ramp3", "exp3"):
            for bg in (10, 50, 200):
                for s in range(1, 5):
                    yield dict(scene="sky", h=64, w=64, sig=0, bg=bg, seed=200 + s,
                               bgk=bgk)
            for sc in ("sphere", "fence", "mostly_sky"):
                for sig, bg in [(5, 50), (2, 50), (10, 2)]:
                    for s in (1, 2):
                        yield dict(scene=sc, h=64, w=64, sig=sig, bg=bg, seed=s, bgk=bgk)
    elif group == "pulse":
        for pm in (1.3, 0.77):
            for sc in ("sphere", "edge45", "steep10cm"):
                for sig, bg in CELLS:
                    for s in (1, 2):
                        yield dict(scene=sc, h=64, w=64, sig=sig, bg=bg, seed=s,
                                   pulse_mult=pm)
    elif group == "shape":
        for h, w in ((48, 80), (16, 16)):
            for sc in ("sphere", "edge45", "triangle", "fence"):
                for sig, bg in CELLS:
                    for s in seeds:
                        yield dict(scene=sc, h=h, w=w, sig=sig, bg=bg, seed=s)
        for s in range(1, 7):
            for bg in (10, 50):
                yield dict(scene="sky", h=16, w=16, sig=0, bg=bg, seed=300 + s)
                yield dict(scene="sky", h=48, w=80, sig=0, bg=bg, seed=300 + s)
    elif group == "mixed":
        for sc in ("edge12", "edge45", "fence", "wire", "triangle", "sphere", "grazing"):
            for sig, bg in CELLS:
                for s in (1, 2):
                    yield dict(scene=sc, h=64, w=64, sig=sig, bg=bg, seed=s, ss=4)
    elif group == "texture":
        for refl in ("flat", "checker", "ramp"):
            for sc in ("edge45", "sphere", "fence", "triangle"):
                for sig, bg in CELLS:
                    for s in (1, 2):
                        yield dict(scene=sc, h=64, w=64, sig=sig, bg=bg, seed=s, refl=refl)
    elif group == "fov":
        for sc in ("flatwall_fov20", "flatwall_fov10"):
            for sig, bg in CELLS:
                for s in (1, 2):
                    yield dict(scene=sc, h=64, w=64, sig=sig, bg=bg, seed=s)
    else:
        raise SystemExit(group)



def report(out, want=None):
    """The tables (markdown) of every DIR/*.jsonl, pooled over seeds."""
    rows = []
    for f in sorted(glob.glob(f"{out}/*.jsonl")):
        with open(f) as fh:
            rows += [{"refl": "flat", **json.loads(x)} for x in fh]   # (older: flat)
    key = ("group", "scene", "h", "w", "sig", "bg", "p_fa", "ss", "pulse_mult", "bgk",
           "refl")
    # (run appends: a frame run again into the same folder replaces its earlier record,
    # the latest kept, so that a re-run is not pooled with the run before it)
    rows = list({tuple(r.get(k) for k in key + ("seed",)): r for r in rows}.values())
    crash = [r for r in rows if "crash" in r]
    rows = [r for r in rows if "crash" not in r]
    g = defaultdict(list)
    for r in rows:
        g[tuple(r[k] for k in key)].append(r)

    def pct(a, b):
        return f"{100 * a / b:.1f}" if b else "-"

    def fmt(x):
        return "-" if x is None else f"{x:.4f}"

    print("| group | scene | HxW | sig,bg | p_fa | ss | pulse x | bg shape | refl | seeds "
          "| RMSE m "
          "| RMSE det m | off>10cm % | det % | 2s det % | 2s und % (n) "
          "| false surf % empty (n) | invented r0/r1 | ramp 3s / >10cm / edge-det "
          "| z99 det | frame s (median) |")
    print("|" + "---|" * 21)
    for k, rs in g.items():
        if want and k[0] not in want:
            continue
        tot = {f: sum(r.get(f, 0) for r in rs) for f in rs[0] if isinstance(rs[0][f], int)}
        m = tot["n_surf"] - tot["n_surf_nan"]
        ns, nd = tot["n_surf"], tot["n_det"]
        rm = (np.sqrt(sum((r["rmse"] or 0) ** 2 * (r["n_surf"] - r["n_surf_nan"]) for r in rs)
                      / m) if m else None)
        rd = np.sqrt(sum((r["rmse_det"] or 0) ** 2 * r["n_det"] for r in rs) / nd) if nd else None
        z99 = max((r.get("z_det_p99", 0) for r in rs), default=0)
        print(f"| {k[0]} | {k[1]} | {k[2]}x{k[3]} | {k[4]},{k[5]} | {k[6]:g} | {k[7]} | {k[8]} "
              f"| {k[9]} | {k[10] or 'flat'} | {len(rs)} | {fmt(rm)} | {fmt(rd)} "
              f"| {pct(tot['off10'], ns)} | {pct(nd, ns)} | {pct(tot['cov_det'], nd)} "
              f"| {pct(tot['cov_und'], tot['n_und'])} ({tot['n_und']}) "
              f"| {pct(tot['false_surf'], tot['n_empty'])} ({tot['false_surf']}/{tot['n_empty']}) "
              f"| {tot['invented_r0']}/{tot['invented_r1']} "
              f"| {tot['ramp']}/{tot.get('ramp10', 0)}/{tot['n_edge_det']} | {z99:.1f} "
              f"| {np.median([r['elapsed'] for r in rs]):.2f} |")
    bad = [(r["scene"], r["seed"], r["warnings"], r["nan_det"], r["bad_sigma"], r["n_surf_nan"])
           for r in rows if r["warnings"] or r["nan_det"] or r["bad_sigma"]]
    print(f"\nframes: {len(rows)}; crashes: {len(crash)} {crash[:3]}")
    print(f"frames with warnings / NaN detected / bad sigma: {len(bad)} {bad[:5]}")
    print("surface pixels with NaN t (no estimate at all):", sum(r["n_surf_nan"] for r in rows))



def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=("run", "report"))
    ap.add_argument("groups", nargs="*")
    ap.add_argument("--out", default="spatial_probe", help="the results' folder")
    ap.add_argument("--keep", default=None, help="also save each frame's estimate here")
    a = ap.parse_intermixed_args()
    if a.what == "report":
        print(f"`python benchmarks/spatial_probe.py report --out {a.out}`; "
              f"{platform.node()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}\n")
        report(a.out, a.groups or None)
        return
    os.makedirs(a.out, exist_ok=True)
    for group in a.groups:
        with open(f"{a.out}/{group}.jsonl", "a") as f:
            for j in jobs(group):
                r = run(**j, keep=a.keep)
                r["group"] = group
                f.write(json.dumps(r) + "\n")
                f.flush()
                print(group, j, f"t={r.get('elapsed', -1):.2f}", flush=True)


if __name__ == "__main__":
    main()
