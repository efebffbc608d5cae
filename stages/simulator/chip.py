"""The simulated chip: per-TDC LSB, INL/DNL, jitter, second-stage codes and the artifact.

A TDC measures ``tau = window_end - t_start`` (reversed timing) and outputs the first-stage
code ``k`` with ``B[k] <= tau < B[k+1]``, where ``B[k] = LSB * (k + INL[k])``. The code
counter has 9 bits, so codes wrap at 512.

- LSB: ``lsb0`` (200-205 ps, Table 3.2) plus up to ``lsb_light_ps`` (40 ps) as the chip's
  light grows (IR drop, section 5.1), most in the middle of the array:
  ``lsb = lsb0 + lsb_light_ps * profile(tdc) * (1 - exp(-n / n_sat))`` with n the
  detections per pixel per cycle of the whole chip (eq. 5.1).
- INL: a pattern that repeats every VCO cycle of 8 codes (identical for all TDCs, scaled per
  TDC), a slow bow, and a small random part per code; DNL < 0.6 LSB, |INL| < 3 LSB.
- TDC jitter: Gaussian, 1.2 LSB FWHM (section 3.2).
- Second stage: ``D2nd`` in ``[n_min, n_max]`` encodes the fine position in the VCO cycle,
  starting at ``n_th`` and wrapping at ``n_max``, so that ``n_th`` is the smallest D2nd
  seen with P1st = 0 and ``pdm`` the smallest with P1st = 4 (section 3.2). Eq. 3.4-3.5
  (the two-stage code) are not used by this project, which ranges on D1st only.
- Artifact (section 3.4): spurious STARTs at a few fixed codes with D2nd above n_max, with
  a per-cycle probability constant over the first 60 TDCs, decreasing, then constant.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.constants import N_CODES, N_CODES_2ND
from stages.models.tcspc import sigma_from_fwhm

_PATTERN8 = np.array([0.25, -0.1, 0.2, -0.3, 0.15, -0.2, 0.1, -0.1])  # INL per phase, LSB


@dataclass(frozen=True)
class Chip:
    """Per-TDC parameters of one simulated chip (arrays of length n_tdc unless noted)."""

    lsb0_ps: np.ndarray
    lsb_light_ps: float
    light_profile: np.ndarray
    n_sat: float
    inl_lsb: np.ndarray          #: (n_tdc, 513): INL at each code boundary, INL[0] = 0
    jitter_fwhm_lsb: float
    n_min: np.ndarray
    n_max: np.ndarray
    n_th: np.ndarray
    artifact_prob: np.ndarray    #: per cycle
    artifact_codes: np.ndarray   #: (n_art,) codes where the artifact lands
    # the chip zoo's knobs (docs/simulator.md); the defaults are the thesis's chip
    #: (n_tdc, 257) cumulative fine-position edges of the block's D2nd codes (row t: its
    #: first width + 1 entries from 0 to 1, padded with 2.0); None: uniform (no DNL)
    d2nd_edges: np.ndarray | None = None
    #: LSB curvature: ps added at n = 1 detection per pixel per cycle, as n^2 x profile
    lsb_quad_ps: float = 0.0
    #: (n_tdc, 512) bool, dead first-stage codes (zero width; their time in a neighbour)
    dead_codes: np.ndarray | None = None
    #: the reset period in ns (the reset peak's height); None: the scene's sensor.reset_ns
    reset_ns: float | None = None
    #: the reset peak's position: tau of a START from the reset period is T + this (ps)
    reset_offset_ps: float = 0.0
    #: the reset peak's extra spread (the enable edge's jitter, rms ps), over the TDC's own
    reset_jitter_ps: float = 0.0
    #: the second stage measures time in the VCO cycle (True), not (phase + frac) / 8
    d2nd_in_time: bool = False

    @property
    def n_tdc(self) -> int:
        return int(self.lsb0_ps.size)

    @property
    def width(self) -> np.ndarray:
        """Second-stage codes per VCO cycle, n_max - n_min + 1."""
        return self.n_max - self.n_min + 1

    def min_d2nd(self, p1st: int) -> np.ndarray:
        """Smallest D2nd a hit with this P1st can have (the wrap at n_max included)."""
        w = self.width
        out = np.empty(self.n_tdc, np.int64)
        if self.d2nd_in_time:  # over every VCO cycle of the counter
            b = np.arange(N_CODES + 1)[None, :] + self.inl_lsb
            c8 = np.arange(0, N_CODES, 8)
            span = b[:, c8 + 8] - b[:, c8]
            lo = (b[:, c8 + p1st] - b[:, c8]) / span
            hi = (b[:, c8 + p1st + 1] - b[:, c8]) / span
            for t in range(self.n_tdc):
                e = (self.d2nd_edges[t, :w[t] + 1] if self.d2nd_edges is not None
                     else np.arange(w[t] + 1) / w[t])
                m = np.flatnonzero(((e[:-1, None] < hi[t][None, :])
                                    & (e[1:, None] > lo[t][None, :])).any(axis=1))
                d2 = self.n_th[t] + m
                out[t] = np.where(d2 > self.n_max[t], d2 - w[t], d2).min()
            return out
        if self.d2nd_edges is not None:
            for t in range(self.n_tdc):  # the codes whose fine interval meets p1st's eighth
                e = self.d2nd_edges[t, :w[t] + 1]
                m = np.flatnonzero((e[:-1] < (p1st + 1) / 8) & (e[1:] > p1st / 8))
                d2 = self.n_th[t] + m
                out[t] = np.where(d2 > self.n_max[t], d2 - w[t], d2).min()
            return out
        for t in range(self.n_tdc):  # once per chip, over 128 TDCs
            # mods floor((p1st + f) * w / 8) for f in [0, 1)
            m = np.arange(p1st * w[t] // 8, -(-(p1st + 1) * w[t] // 8))
            d2 = self.n_th[t] + m
            out[t] = np.where(d2 > self.n_max[t], d2 - w[t], d2).min()
        return out

    @property
    def pdm(self) -> np.ndarray:
        """Smallest D2nd when P1st = 4 (what a density test measures as PDM)."""
        return self.min_d2nd(4)

    def lsb_ps(self, detections_per_pixel_per_cycle: float) -> np.ndarray:
        """LSB of every TDC at a light level (eq. 5.1's n)."""
        n = max(float(detections_per_pixel_per_cycle), 0.0)
        lsb = self.lsb0_ps + self.lsb_light_ps * self.light_profile * -np.expm1(-n / self.n_sat)
        if self.lsb_quad_ps:
            lsb = lsb + self.lsb_quad_ps * self.light_profile * n * n
        return lsb

    def boundaries_s(self, detections_per_pixel_per_cycle: float) -> np.ndarray:
        """(n_tdc, 513) code boundaries in seconds of tau."""
        lsb = self.lsb_ps(detections_per_pixel_per_cycle)[:, None] * 1e-12
        return lsb * (np.arange(N_CODES + 1)[None, :] + self.inl_lsb)

    def dnl_lsb(self) -> np.ndarray:
        """(n_tdc, 512) DNL of every code."""
        return np.diff(self.inl_lsb, axis=1)

    def jitter_s(self, detections_per_pixel_per_cycle: float) -> np.ndarray:
        return sigma_from_fwhm(self.jitter_fwhm_lsb
                               * self.lsb_ps(detections_per_pixel_per_cycle) * 1e-12)

    def window_truth(self, detections_per_pixel_per_cycle: float, window_s: float):
        """The LSB as the window over the code span, and the INL against it.

        ``x_T`` is where tau = T falls on the code axis; ``lsb = T / x_T``;
        ``inl[k] = B[k] / lsb - k``. This is what a density test measures (the INL bow
        beyond the window is invisible to it).
        """
        b = self.boundaries_s(detections_per_pixel_per_cycle)
        k = np.array([np.searchsorted(row, window_s, side="right") - 1 for row in b])
        rows = np.arange(self.n_tdc)
        x_t = k + (window_s - b[rows, k]) / (b[rows, k + 1] - b[rows, k])
        lsb = window_s / x_t
        inl = b[:, :N_CODES] / lsb[:, None] - np.arange(N_CODES)[None, :]
        return lsb, x_t, inl

    def truth(self, detections_per_pixel_per_cycle: float, window_s: float = 80e-9) -> dict:
        """What a calibration should find, for the capture's sidecar."""
        lsb_w, x_t, inl_w = self.window_truth(detections_per_pixel_per_cycle, window_s)
        return {
            "lsb_window_ps": np.round(lsb_w * 1e12, 6).tolist(),
            "x_t": np.round(x_t, 6).tolist(),
            "inl_window_lsb": np.round(inl_w, 5).tolist(),
            "lsb_ps": np.round(self.lsb_ps(detections_per_pixel_per_cycle), 6).tolist(),
            "lsb0_ps": np.round(self.lsb0_ps, 6).tolist(),
            "lsb_light_ps": self.lsb_light_ps, "n_sat": self.n_sat,
            "light_profile": np.round(self.light_profile, 6).tolist(),
            "inl_lsb": np.round(self.inl_lsb[:, :N_CODES], 5).tolist(),
            "n_min": self.n_min.tolist(), "n_max": self.n_max.tolist(),
            "n_th": self.n_th.tolist(), "pdm": self.pdm.tolist(),
            "artifact_prob": self.artifact_prob.tolist(),
            "artifact_codes": self.artifact_codes.tolist(),
            "jitter_fwhm_lsb": self.jitter_fwhm_lsb,
            **self.zoo_truth(),
        }

    def zoo_truth(self) -> dict:
        """The chip zoo's knobs where they differ from the thesis's chip (else nothing)."""
        out = {}
        if self.d2nd_edges is not None:
            out["d2nd_widths"] = [np.round(np.diff(self.d2nd_edges[t, :w + 1]) * w, 5).tolist()
                                  for t, w in enumerate(self.width)]
        if self.lsb_quad_ps:
            out["lsb_quad_ps"] = self.lsb_quad_ps
        if self.dead_codes is not None:
            out["dead_codes"] = [np.flatnonzero(r).tolist() for r in self.dead_codes]
        if self.reset_ns is not None:
            out["reset_ns"] = self.reset_ns
        if self.reset_offset_ps:
            out["reset_offset_ps"] = self.reset_offset_ps
        if self.reset_jitter_ps:
            out["reset_jitter_ps"] = self.reset_jitter_ps
        if self.d2nd_in_time:
            out["d2nd_in_time"] = True
        return out

    def reset_jitter_s(self, detections_per_pixel_per_cycle: float) -> np.ndarray:
        """The spread of the reset peak: the TDC's jitter and the enable edge's."""
        j = self.jitter_s(detections_per_pixel_per_cycle)
        if not self.reset_jitter_ps:
            return j
        return np.hypot(j, self.reset_jitter_ps * 1e-12)


def make_chip(n_tdc: int = 128, rng: np.random.Generator | int | None = 0, *,
              lsb_range_ps=(200.0, 205.0), lsb_light_ps: float = 40.0, n_sat: float = 0.25,
              inl_scale: float = 1.0, jitter_fwhm_lsb: float = 1.2,
              artifact_rate: float = 2.9e-4, artifact_codes=(41, 169, 297),
              n_min_range=(12, 28), width_range=(110, 150), d2nd_dnl: float = 0.0,
              dead_codes: int = 0, lsb_quad_ps: float = 0.0, reset_ns: float | None = None,
              reset_offset_ps: float = 0.0, reset_jitter_ps: float = 0.0,
              d2nd_in_time: bool = False, dnl_random_lsb: float = 0.04,
              bow_lsb: float = 1.2) -> Chip:
    """A chip with the thesis's characteristics, drawn from ``rng``.

    ``inl_scale = 0`` gives an ideal TDC (uniform codes); ``artifact_rate = 0`` none.
    The chip zoo's knobs (docs/simulator.md, :func:`random_chip`) default to the thesis's
    chip, and draw nothing from ``rng`` unless set, so the default chip is unchanged:

    - ``n_min_range``, ``width_range``: where the second stage's block [Nmin, Nmax] lies
      (integers drawn in ``[lo, hi)``).
    - ``d2nd_dnl``: the second stage's DNL, the largest deviation of a D2nd code's width
      from the block's mean (0.3: widths 0.7-1.3): 70 % a pattern repeating every 8 codes
      of D2nd (its 4-stage differential ring, as the first stage's), 30 % random per code;
      no width below 0.3 (no empty code inside the block).
    - ``dead_codes``: first-stage codes per TDC of zero width (never output), their time
      merged into a neighbour (one of the two, at random), among codes 12-360.
    - ``lsb_quad_ps``: LSB curvature, ``lsb_quad_ps * profile * n^2`` added to eq. 5.1's
      light dependence (``n_sat`` shapes the 1 - exp part).
    - ``reset_ns``: the reset period (the reset peak's height: its STARTs are the light of
      this period); None keeps the scene's ``sensor.reset_ns``.
    - ``reset_offset_ps``: a START from the reset period is at tau = T + this (the TDC's
      enable released off the window's opening); 0 is the thesis's chip (tau = T).
    - ``reset_jitter_ps``: extra rms spread of the reset peak (the enable edge's jitter).
    - ``d2nd_in_time``: the second stage measures the time since the VCO cycle began
      (its 8 phases as wide as the first stage's INL makes them, PDM where phase 4 starts
      in time), not ``(phase + frac) / 8`` (every phase an eighth of the block, so a
      narrow phase's eighth of D2nd codes is sparse: the default, kept for its bytes).
    - ``dnl_random_lsb``: the random part of every code's DNL (rms, before ``inl_scale``;
      the INL is its running sum, pinned at both ends); real chips have 0.05-0.1 LSB.
    - ``bow_lsb``: the largest amplitude of the slow INL bow (a half sine over the codes,
      amplitude drawn in +-this); real chips bow by a few LSB.

    Examples
    --------
    >>> chip = make_chip(rng=1)
    >>> bool(np.abs(chip.dnl_lsb()).max() < 0.6 and np.abs(chip.inl_lsb).max() < 3)
    True
    """
    rng = np.random.default_rng(rng)
    t = np.arange(n_tdc)
    lsb0 = rng.uniform(*lsb_range_ps, n_tdc)
    profile = 0.5 + 0.5 * np.sin(np.pi * (t + 0.5) / n_tdc)  # most in the middle
    k = np.arange(N_CODES + 1)
    scale = inl_scale * rng.uniform(0.7, 1.0, n_tdc)[:, None]
    periodic = _PATTERN8[k % 8] - _PATTERN8[0]
    bow = bow_lsb * np.sin(np.pi * k / N_CODES)[None, :] * rng.uniform(-1, 1, n_tdc)[:, None]
    rand = np.cumsum(rng.normal(0, dnl_random_lsb, (n_tdc, N_CODES + 1)), axis=1)
    rand -= np.linspace(0, 1, N_CODES + 1)[None, :] * rand[:, -1:]  # pinned at both ends
    inl = scale * (periodic[None, :] + bow + rand)
    inl -= inl[:, :1]
    # keep every code's width positive and the DNL within spec
    dnl = np.clip(np.diff(inl, axis=1), -0.55, 0.55)
    inl = np.concatenate([np.zeros((n_tdc, 1)), np.cumsum(dnl, axis=1)], axis=1)
    n_min = rng.integers(*n_min_range, n_tdc)
    width = rng.integers(*width_range, n_tdc)
    n_max = n_min + width - 1
    if np.any(n_max >= N_CODES_2ND - 1):
        raise ValueError("the second stage's block must end below 255 (the artifact lies "
                         "above it)")
    # n_th leaves room for the P1st = 0 eighth below the wrap: then n_th is min D2nd there
    n_th = n_min + rng.integers(0, width - width // 8 - 1)
    prob = np.where(t < 60, 1.0, np.where(t < 100, 1 - 0.8 * (t - 60) / 40, 0.2))
    dead = None
    if dead_codes:
        inl, dead = _kill_codes(inl, int(dead_codes), rng)
    edges = _d2nd_edges(d2nd_dnl, n_th, n_max, width, rng) if d2nd_dnl else None
    return Chip(lsb0, lsb_light_ps, profile, n_sat, inl, jitter_fwhm_lsb, n_min, n_max,
                n_th, artifact_rate * prob, np.asarray(artifact_codes, np.int64),
                edges, float(lsb_quad_ps), dead, None if reset_ns is None else float(reset_ns),
                float(reset_offset_ps), float(reset_jitter_ps), bool(d2nd_in_time))


#: First-stage codes a dead code may be (every third: a dead code's neighbours are live).
DEAD_CANDIDATES = np.arange(12, 361, 3)


def _kill_codes(inl: np.ndarray, n_dead: int, rng: np.random.Generator):
    """``n_dead`` codes per TDC of zero width, their width given to a neighbour."""
    w = np.diff(inl, axis=1) + 1.0
    dead = np.zeros((inl.shape[0], N_CODES), bool)
    for t in range(inl.shape[0]):  # once per chip
        for k in rng.choice(DEAD_CANDIDATES, n_dead, replace=False):
            j = k + (1 if rng.random() < 0.5 else -1)
            w[t, j] += w[t, k]
            w[t, k] = 0.0
            dead[t, k] = True
    k = np.arange(N_CODES + 1)
    inl = np.concatenate([np.zeros((inl.shape[0], 1)), np.cumsum(w, axis=1)], axis=1) - k
    return inl, dead


def place_dead_codes(chip: Chip, placements: dict) -> Chip:
    """``chip`` with dead codes placed, not drawn: ``placements`` maps a TDC to its
    ``(code, neighbour)`` pairs, each code given zero width and its width added to
    ``neighbour`` (``code +- 1``), as ``make_chip(dead_codes=)`` does at random. For tests
    that put a dead code where an estimator is weakest (next to the reset peak).

    >>> chip = place_dead_codes(make_chip(2, 1), {1: [(300, 301)]})
    >>> float(chip.dnl_lsb()[1, 300]), int(chip.dead_codes.sum())
    (-1.0, 1)
    """
    import dataclasses

    w = np.diff(chip.inl_lsb, axis=1) + 1.0
    dead = (np.zeros((chip.n_tdc, N_CODES), bool) if chip.dead_codes is None
            else chip.dead_codes.copy())
    for t, pairs in placements.items():
        for k, j in pairs:
            if abs(j - k) != 1 or dead[t, k] or dead[t, j]:
                raise ValueError(f"TDC {t}: dead code {k} into {j}: not a live neighbour")
            w[t, j] += w[t, k]
            w[t, k] = 0.0
            dead[t, k] = True
    k = np.arange(N_CODES + 1)
    inl = np.concatenate([np.zeros((chip.n_tdc, 1)), np.cumsum(w, axis=1)], axis=1) - k
    return dataclasses.replace(chip, inl_lsb=inl, dead_codes=dead)


def _d2nd_edges(amplitude: float, n_th, n_max, width, rng: np.random.Generator):
    """(n_tdc, 257) cumulative fine-position edges of each TDC's D2nd codes in fine order
    (mod 0 at n_th): widths 1 + DNL, DNL = amplitude x (0.7 x a pattern of D2nd % 8 + 0.3
    x random), none below 0.3, normalised to the VCO cycle; padded with 2.0."""
    pattern = rng.uniform(-1, 1, 8)
    out = np.full((n_th.size, N_CODES_2ND + 1), 2.0)
    for t, w in enumerate(width):  # once per chip
        m = np.arange(w)
        d2 = n_th[t] + m
        d2 = np.where(d2 > n_max[t], d2 - w, d2)
        dnl = amplitude * (0.7 * pattern[d2 % 8] + 0.3 * rng.uniform(-1, 1, w))
        widths = np.maximum(1.0 + dnl, 0.3)
        e = np.concatenate([[0.0], np.cumsum(widths)]) / widths.sum()
        e[-1] = 1.0
        out[t, :w + 1] = e
    return out


def second_stage(chip: Chip, tdc: np.ndarray, code: np.ndarray, frac: np.ndarray,
                 boundaries: np.ndarray | None = None) -> np.ndarray:
    """D2nd of hits: the fine position ((code % 8) + frac) / 8 in the VCO cycle (in time
    where ``chip.d2nd_in_time``, on ``boundaries``, the simulator's), on the second
    stage's scale from n_th, wrapping at n_max back to n_min."""
    w = chip.width[tdc]
    if chip.d2nd_in_time:
        b = (np.arange(N_CODES + 1)[None, :] + chip.inl_lsb) if boundaries is None \
            else boundaries
        k8 = code - code % 8
        lo, hi = b[tdc, k8], b[tdc, k8 + 8]
        f = (b[tdc, code] + frac * (b[tdc, code + 1] - b[tdc, code]) - lo) / (hi - lo)
        f = np.minimum(np.maximum(f, 0.0), 1.0 - 1e-16)
    else:
        f = ((code % 8) + frac) / 8
    if chip.d2nd_edges is None:
        mod = np.minimum(np.floor(f * w), w - 1).astype(np.int64)
    else:  # the code whose fine interval holds the position (as the compiled kernel)
        mod = np.empty(f.size, np.int64)
        for t in np.unique(tdc):
            sel = tdc == t
            mod[sel] = np.searchsorted(chip.d2nd_edges[t], f[sel], side="right") - 1
        mod = np.clip(mod, 0, w - 1)
    d2 = chip.n_th[tdc] + mod
    return np.where(d2 > chip.n_max[tdc], d2 - w, d2)


def artifact_d2nd(chip: Chip, tdc: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """D2nd of artifact words: above n_max (section 3.4)."""
    lo = chip.n_max[tdc] + 1
    return lo + np.floor(rng.random(tdc.size) * (N_CODES_2ND - lo)).astype(np.int64)


#: The chip zoo (docs/simulator.md): the range of every knob :func:`random_chip` draws
#: (uniformly; integers in [lo, hi]). Physically motivated, wider than the thesis's chip.
ZOO_RANGES = {
    # LSB at no light (Table 3.2: 200-205 ps on the thesis's chip; the thesis's first
    # measurement put the reset peak at codes 300-350): the reset peak at x_T = T / LSB
    "lsb_centre_ps": (185.0, 235.0),
    "lsb_spread_ps": (1.0, 8.0),         # across the array
    "lsb_light_ps": (10.0, 60.0),        # growth with light (section 5.1: up to 40 ps)
    "n_sat": (0.1, 1.5),                 # light scale of the 1 - exp growth (thesis's: 0.25)
    "lsb_quad_ps": (-15.0, 15.0),        # curvature beyond it, ps at n = 1
    "inl_scale": (0.5, 1.3),             # |DNL| stays < 0.55 LSB (clipped)
    "jitter_fwhm_lsb": (0.8, 1.8),       # section 3.2: 1.2
    "d2nd_dnl": (0.05, 0.5),             # second-stage DNL, tens of percent
    "n_min_lo": (2, 60),                 # Nmin drawn in [lo, lo + 16)
    "width_lo": (80, 160),               # Nmax - Nmin + 1 in [lo, lo + 40), Nmax < 254
    "artifact_rate": (0.0, 3e-3),        # per cycle (the thesis's chip: 2.9e-4)
    "n_artifact_codes": (1, 4),
    "dead_codes": (0, 3),                # per TDC (FPGA and VCO TDCs have missing codes)
    "reset_ns": (8.0, 60.0),             # the reset peak's height (thesis's scenes: 20 ns)
    "reset_jitter_ps": (0.0, 150.0),     # the reset peak's extra spread
    "reset_offset_ps": (0.0, 0.0),       # off in the sweep: see docs/simulator.md
    "d2nd_in_time": (1, 1),              # 1: the second stage measures time (physical)
}

#: What real chips have and :data:`ZOO_RANGES` leaves at the thesis's chip (issue 33): a
#: random DNL of 0.05-0.1 LSB per code, a slow INL bow of a few LSB. ``random_chip(seed,
#: ranges=REAL_CHIP_RANGES)`` draws them from a stream of their own, so every other knob of
#: a seed is what :data:`ZOO_RANGES` draws.
REAL_CHIP_RANGES = {"dnl_random_lsb": (0.05, 0.1), "bow_lsb": (2.0, 4.0)}
#: Knobs drawn only when ``ranges`` names them (their own stream; else make_chip's default).
EXTRA_KNOBS = ("dnl_random_lsb", "bow_lsb")


def random_chip(seed: int | np.random.Generator, n_tdc: int = 16,
                ranges: dict | None = None) -> tuple[Chip, dict]:
    """A chip of the zoo: every knob drawn from ``ranges`` (defaults :data:`ZOO_RANGES`,
    any subset overridden) with a generator seeded by ``seed``. Returns the chip and the
    knobs drawn (what a failing sweep reports to reproduce it). Overriding one range (or
    fixing a knob, ``(x, x)``) leaves the other knobs of a seed as they were.

    >>> chip, knobs = random_chip(3, n_tdc=4)
    >>> chip.n_tdc, set(ZOO_RANGES) <= set(knobs)
    (4, True)
    """
    r = {**ZOO_RANGES, **(ranges or {})}
    extra = {name: r.pop(name) for name in EXTRA_KNOBS if name in r}
    rng = np.random.default_rng(seed)

    def draw(name):
        lo, hi = r[name]
        if isinstance(lo, int) and isinstance(hi, int):
            return int(rng.integers(lo, hi + 1))
        return float(rng.uniform(lo, hi))  # drawn even when fixed: the others stay put

    k = {name: draw(name) for name in r}
    k["width_lo"] = min(k["width_lo"], N_CODES_2ND - 2 - (k["n_min_lo"] + 16) - 40 + 1)
    codes = np.sort(rng.choice(np.arange(8, 330), k["n_artifact_codes"], replace=False))
    k["artifact_codes"] = codes.tolist()
    # a seed's own stream for them (a generator given as the seed draws them itself)
    own = np.random.default_rng([int(seed), 33]) if isinstance(seed, int | np.integer) else rng
    k.update({name: float(own.uniform(*extra[name])) for name in EXTRA_KNOBS if name in extra})
    c = k["lsb_centre_ps"]
    chip = make_chip(
        n_tdc, rng, lsb_range_ps=(c - k["lsb_spread_ps"] / 2, c + k["lsb_spread_ps"] / 2),
        lsb_light_ps=k["lsb_light_ps"], n_sat=k["n_sat"], inl_scale=k["inl_scale"],
        jitter_fwhm_lsb=k["jitter_fwhm_lsb"], artifact_rate=k["artifact_rate"],
        artifact_codes=codes, n_min_range=(k["n_min_lo"], k["n_min_lo"] + 16),
        width_range=(k["width_lo"], k["width_lo"] + 40), d2nd_dnl=k["d2nd_dnl"],
        dead_codes=k["dead_codes"], lsb_quad_ps=k["lsb_quad_ps"], reset_ns=k["reset_ns"],
        reset_offset_ps=k["reset_offset_ps"], reset_jitter_ps=k["reset_jitter_ps"],
        d2nd_in_time=bool(k["d2nd_in_time"]),
        **{name: k[name] for name in EXTRA_KNOBS if name in k})
    return chip, k
