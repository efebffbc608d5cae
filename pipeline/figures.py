"""The thesis's chapter-2 figures, regenerated from the models (PNG, matplotlib Agg)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy.constants import c as C_LIGHT  # noqa: E402

from pipeline.atomic import atomic_path  # noqa: E402
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
