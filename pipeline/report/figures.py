"""The thesis's chapter-2 figures, regenerated from the models (PNG, matplotlib Agg)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy.constants import c as C_LIGHT  # noqa: E402

from pipeline.io.atomic import atomic_path  # noqa: E402
from stages.models.performance import (  # noqa: E402
    TABLE_2_2,
    SystemSpec,
    moving_target_histogram,
    predict,
)
from stages.models.tcspc import first_photon_histogram, peak_shift  # noqa: E402


def _save(fig, path: Path) -> Path:
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    plt.close(fig)
    return path


def figure_2_2(path) -> Path:
    """Peak position distortion against M (eq. 2.6, physics-corrected), in sigma units."""
    m = np.logspace(-3, 1, 200)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.semilogx(m, peak_shift(m), lw=2)
    ax.set_xlabel("M, expected signal detections per cycle")
    ax.set_ylabel("(t_peak - TOF) / sigma")
    ax.set_title("Figure 2.2: pile-up pulls the peak early")
    ax.grid(True, which="both", alpha=0.3)
    return _save(fig, path)


def figure_2_13(path, distance_m=None) -> Path:
    """P of detecting the peak against distance for the eight configurations of Table 2.2."""
    d = np.arange(0.25, 60, 0.5) if distance_m is None else np.asarray(distance_m)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for i, spec in enumerate(TABLE_2_2, start=1):
        ax.plot(d, predict(spec, d)["p_detect"], label=f"{i}", lw=1.6)
    ax.set_xlabel("distance (m)")
    ax.set_ylabel("P (eq. 2.44-2.48)")
    ax.set_title("Figure 2.13: peak detection probability (Table 2.2, no gating)")
    ax.legend(title="config", ncol=4, fontsize=8)
    ax.grid(True, alpha=0.3)
    return _save(fig, path)


def figure_2_16(path) -> Path:
    """Histograms of a target moving at 0, 50 and 100 m/s (2000 samples at 1 MHz)."""
    spec = SystemSpec(samples=2000, tdc_resolution_s=20e-12, jitter_s=80e-12,
                      ambient_lux=0.0, pde=0.02)
    fig, ax = plt.subplots(figsize=(7, 4))
    for v in (0.0, 50.0, 100.0):
        edges, counts = moving_target_histogram(spec, 10.0, v, 1e6, window_s=4e-9,
                                                samples=2000)
        ax.step(edges[:-1] * 1e9, counts, where="post", label=f"{v:g} m/s")
    ax.set_xlabel("arrival time in the gate (ns)")
    ax.set_ylabel("expected counts per bin")
    ax.set_title("Figure 2.16: a moving target spreads the peak (round-trip TOF)")
    ax.legend()
    return _save(fig, path)


def figure_2_18(path) -> Path:
    """Histograms at TOF 60, 120, 180 ns without gating (a) and with a 50 ns gate (b)."""
    spec = SystemSpec(ambient_lux=2000.0, samples=10_000, pde=0.02)
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for tof_ns in (60, 120, 180):
        x = tof_ns * 1e-9 * C_LIGHT / 2
        m = float(spec.signal_per_cycle(x)) * 40
        h = first_photon_histogram(m, tof_ns * 1e-9, spec.jitter_s, spec.background_hz,
                                   200e-9, spec.tdc_resolution_s)
        a.plot(h.edges_s[:-1] * 1e9, h.counts(spec.samples), lw=0.8, label=f"TOF {tof_ns} ns")
        g = first_photon_histogram(m, 25e-9, spec.jitter_s, spec.background_hz, 50e-9,
                                   spec.tdc_resolution_s)
        b.plot(g.edges_s[:-1] * 1e9 + tof_ns - 25, g.counts(spec.samples), lw=0.8,
               label=f"TOF {tof_ns} ns")
    a.set_title("(a) without gating: window opens at the pulse")
    b.set_title("(b) with a 50 ns gate around the return")
    for ax in (a, b):
        ax.set_xlabel("arrival time after the laser (ns)")
        ax.set_ylabel("expected counts per 200 ps bin")
        ax.legend()
    fig.suptitle("Figure 2.18: effect of gating")
    return _save(fig, path)


def all_figures(out_dir) -> list[Path]:
    out = Path(out_dir)
    return [figure_2_2(out / "figure_2_2.png"), figure_2_13(out / "figure_2_13.png"),
            figure_2_16(out / "figure_2_16.png"), figure_2_18(out / "figure_2_18.png")]


def density_figure(res, path) -> Path:
    """DNL and INL of every TDC (like Figures H.3-H.5): all curves, worst case highlighted."""
    fig, (a, b) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    k = np.arange(res.dnl_lsb.shape[1])
    for t in np.flatnonzero(res.ok):
        a.plot(k, res.dnl_lsb[t], lw=0.3, alpha=0.3, color="C0")
        b.plot(k, res.inl_lsb[t], lw=0.3, alpha=0.3, color="C1")
    worst = int(np.nanargmax(np.nanmax(np.abs(res.inl_lsb), axis=1)))
    b.plot(k, res.inl_lsb[worst], lw=1.2, color="k", label=f"worst INL: TDC {worst}")
    a.set_ylabel("DNL (LSB)")
    b.set_ylabel("INL (LSB)")
    b.set_xlabel("code (D1st)")
    b.legend()
    a.set_title(f"density test: {res.ok.sum()} TDCs, LSB "
                f"{np.nanmean(res.lsb_s) * 1e12:.2f} ps mean")
    return _save(fig, path)


def lsb_figure(n, lsbs_ps, fit, path) -> Path:
    """LSB against light for every TDC with its cubic (like Figures 5.1-5.2)."""
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    x = np.linspace(min(n), max(n), 100)
    curves = fit.lsb_ps(x)
    for t in range(lsbs_ps.shape[0]):
        a.plot(n, lsbs_ps[t], "o", ms=2, alpha=0.3, color="C0")
        a.plot(x, curves[t], lw=0.4, alpha=0.3, color="C1")
    a.set_xlabel("detections per pixel per cycle (eq. 5.1)")
    a.set_ylabel("LSB (ps)")
    a.set_title("Figure 5.1: LSB against light, all TDCs")
    b.plot(n, lsbs_ps[0], "o", label="density tests")
    b.plot(x, curves[0], label="cubic fit")
    b.set_xlabel("detections per pixel per cycle")
    b.set_title("Figure 5.2: the first TDC")
    b.legend()
    return _save(fig, path)


def speed_error_figure(df, path) -> Path:
    """Range estimators' speed against error (RMSE over the CRLB), one point per cell of
    the grid that counts (detection > 90 %, SBR >= 1), stars at the medians."""
    import polars as pl

    fig, ax = plt.subplots(figsize=(7, 4.5))
    good = df.filter((pl.col("detected") > 0.9) & (pl.col("sbr") >= 1))
    for est in good["estimator"].unique().sort():
        d = good.filter(pl.col("estimator") == est)
        pts = ax.scatter(d["hist_per_s"], d["rmse_over_crlb"], s=8, alpha=0.4, label=est)
        ax.scatter([d["hist_per_s"].median()], [d["rmse_over_crlb"].median()], s=160,
                   marker="*", edgecolor="k", color=pts.get_facecolor()[0][:3])
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.axhline(1.2, ls="--", c="grey", lw=0.8)
    ax.set_xlabel("histograms per second (one core)")
    ax.set_ylabel("RMSE / CRLB")
    ax.set_title("range estimators: speed against error (stars: medians)")
    ax.legend()
    return _save(fig, path)


def street_figure(tdc, distance_m, detected, truth, hist_tdc, hist_counts, path) -> Path:
    """What the demo found in the street scene: each pixel's median range against the
    targets' true distances (left), and one pixel's histogram of first-stage codes (right,
    reversed timing: early photons have high codes, the reset peak sits at the top).

    ``truth``: (name, first pixel, last pixel, distance_m) per target.
    """
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 3.6), gridspec_kw={"width_ratios": [3, 2]})
    det = np.asarray(detected, bool)
    ax.plot(np.asarray(tdc)[det], np.asarray(distance_m)[det], ".", ms=4, label="measured")
    for name, lo, hi, d in truth:
        ax.hlines(d, lo, hi, colors="k", lw=1)
        ax.annotate(name, ((lo + hi) / 2, d), textcoords="offset points", xytext=(0, 5),
                    ha="center", fontsize=8)
    ax.set_xlabel("pixel (TDC address)")
    ax.set_ylabel("distance, m")
    ax.set_title("street scene through the daemon: median range per pixel")
    ax.grid(alpha=0.3)
    bx.semilogy(np.arange(len(hist_counts)), np.maximum(hist_counts, 0.5), lw=0.8)
    bx.set_xlabel("first-stage code D1st (~200 ps)")
    bx.set_ylabel("hits")
    bx.set_title(f"pixel {hist_tdc}: histogram of one measurement")
    bx.grid(alpha=0.3, which="both")
    return _save(fig, path)
