"""The simulator as a source: a scene and a chip in, batches of raw words out, with truth.

The word stream depends only on (scene, chip, seed, engine): cycles are drawn in chunks of
``CHUNK_CYCLES`` with a generator seeded by ``(seed, chunk index)``, so the same seed gives
the same bytes however a consumer batches them, and chunks can be drawn in any order.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from scipy.constants import c as C_LIGHT

from schemas.constants import ARTIFACT, HIT, INVALID_PHASE, MALFORMED, N_CLASSES, NO_HIT
from stages.codec import BUBBLE_CODES, MARKER_BITS, encode_words
from stages.models.scene import SceneModel
from stages.models.tcspc import combined_sigma, first_photon_histogram, sigma_from_fwhm
from stages.simulator.chip import Chip, second_stage
from stages.simulator.engines import (
    KIND_ARTIFACT,
    CodeTable,
    Events,
    FastEngine,
    Optics,
    ReferenceEngine,
    Starts,
    digitize,
    draw_tails,
    fast_chunk_numba,
    numba,
)

CHUNK_CYCLES = 2048
_ENGINE_IDS = {"fast": 0, "reference": 1}


def optics_from_scene(sm: SceneModel) -> tuple[Optics, float]:
    """The per-TDC optics of a scene, and the SPAD's share of the jitter (seconds)."""
    las, s = sm.scene.laser, sm.scene.sensor
    spad = s.spad_jitter_ps * 1e-12
    sigma = float(combined_sigma(sigma_from_fwhm(las.fwhm_ps * 1e-12), las.jitter_ps * 1e-12,
                                 spad))
    tof = np.nan_to_num(sm.tof_in_window_s, nan=0.0)
    drift = np.zeros(s.n_pixels)
    for t in sm.scene.targets:
        drift[t.pixels[0]:t.pixels[1] + 1] = 2 * t.velocity_m_s * s.readout_us * 1e-6 / C_LIGHT
    extra_m = extra_tof = None
    if sm.returns_m is not None and sm.returns_m.shape[1] > 1 and np.any(sm.returns_m[:, 1:]):
        extra_m = sm.returns_m[:, 1:].copy()
        extra_tof = np.nan_to_num(sm.returns_tof_s[:, 1:], nan=0.0)
    return Optics(sm.m_signal, tof, sigma, sm.bg_rate_hz, sm.window_s, s.reset_ns * 1e-9,
                  drift if np.any(drift) else None, extra_m, extra_tof), spad


def detections_per_pixel_per_cycle(optics: Optics) -> float:
    """Expected STARTs per pixel per cycle over the chip (eq. 5.1's n), reset peak included."""
    h = first_photon_histogram(optics.m_signal, optics.tof_s, optics.sigma_s, optics.bg_hz,
                               optics.window_s, optics.window_s / 64, optics.reset_s)
    return float(np.mean(1 - h.p_none))


@dataclass
class SimulationResult:
    """Running totals of what the simulator emitted (the truth of the class counts)."""

    class_counts: np.ndarray  #: (N_CLASSES, n_tdc)
    cycles: int = 0


class Simulator:
    """Raw words of a scene seen by a chip.

    Parameters
    ----------
    scene_model : SceneModel
        From :func:`stages.models.scene.evaluate`.
    chip : Chip
    seed : int
    engine : {"fast", "reference"}
        Moving targets need "reference".
    malformed_rate, invalid_rate : float
        Fraction of words to corrupt (for tests of the bad-input paths).
    """

    def __init__(self, scene_model: SceneModel, chip: Chip, seed: int = 0,
                 engine: str = "fast", malformed_rate: float = 0.0, invalid_rate: float = 0.0,
                 compiled: bool | None = None, optics: Optics | None = None,
                 spad_sigma_s: float | None = None):
        if scene_model is not None and chip.n_tdc != scene_model.scene.sensor.n_pixels:
            raise ValueError(f"chip has {chip.n_tdc} TDCs, the scene's sensor "
                             f"{scene_model.scene.sensor.n_pixels}")
        if engine not in _ENGINE_IDS:
            raise ValueError(f"engine must be one of {sorted(_ENGINE_IDS)}, found {engine!r}")
        self.sm, self.chip, self.seed, self.engine_name = scene_model, chip, int(seed), engine
        if scene_model is not None:
            self.optics, spad = optics_from_scene(scene_model)
        elif optics is not None:
            self.optics = optics
            spad = optics.sigma_s if spad_sigma_s is None else spad_sigma_s
        else:
            raise ValueError("Simulator needs a scene model or optics")
        if chip.reset_ns is not None:  # the zoo's chip has its own reset period
            self.optics = dataclasses.replace(self.optics, reset_s=chip.reset_ns * 1e-9)
        self.light = detections_per_pixel_per_cycle(self.optics)
        self.boundaries = chip.boundaries_s(self.light)
        self.codes = CodeTable(self.boundaries)
        self.jitter = chip.jitter_s(self.light)
        self.reset_jitter = chip.reset_jitter_s(self.light)
        self.engine = (FastEngine(chip, self.optics, self.boundaries) if engine == "fast"
                       else ReferenceEngine(chip, self.optics, self.boundaries, spad))
        self.malformed_rate, self.invalid_rate = malformed_rate, invalid_rate
        # the fast engine's per-START work runs compiled where numba is installed; the numpy
        # path computes the same words from the same random numbers (tested to agree)
        self.compiled = (numba is not None) if compiled is None else compiled
        if self.compiled and numba is None:
            raise RuntimeError("compiled=True needs numba")
        n = chip.n_tdc
        self._template = encode_words(0, 0, 0, 0, np.arange(n))
        self.result = SimulationResult(np.zeros((N_CLASSES, n), np.int64))

    @classmethod
    def from_optics(cls, optics: Optics, chip: Chip, seed: int = 0, engine: str = "fast",
                    spad_sigma_s: float | None = None, **kw) -> Simulator:
        """A simulator of given optics (no scene): for benchmarks and tests of regimes."""
        return cls(None, chip, seed, engine, optics=optics, spad_sigma_s=spad_sigma_s, **kw)

    @property
    def n_tdc(self) -> int:
        return self.chip.n_tdc

    def chunk(self, index: int, n_cycles: int = CHUNK_CYCLES) -> tuple[np.ndarray, np.ndarray]:
        """Words of chunk ``index`` (cycles ``index * CHUNK_CYCLES`` onwards) and their
        per-TDC class counts. Deterministic in (seed, index)."""
        rng = np.random.default_rng([self.seed, index, _ENGINE_IDS[self.engine_name]])
        n = self.n_tdc
        if isinstance(self.engine, ReferenceEngine):
            starts = self.engine.draw(rng, n_cycles, index * CHUNK_CYCLES)
            ev = Events(starts.index, np.empty(0))
        else:
            ev = self.engine.events(rng, n_cycles)
            starts = None if self.compiled else self.engine.starts(ev)
        tdc = ev.tdc if ev.tdc is not None else ev.index % n
        if starts is None:
            words_t = np.repeat(self._template, n_cycles).reshape(n, n_cycles)
            art = fast_chunk_numba(self.engine, self.chip, self.codes, self.jitter, ev, rng,
                                   words_t, self.reset_jitter)
            words = np.ascontiguousarray(words_t.T).reshape(-1)
        else:
            words = np.tile(self._template, n_cycles)
            art = starts.kind == KIND_ARTIFACT
            z, r = draw_tails(rng, art)
            tdc, code, frac = digitize(self.codes, self.jitter, self.optics.window_s, starts,
                                       n, z, self.chip.reset_offset_ps * 1e-12,
                                       self.reset_jitter)
            d2 = second_stage(self.chip, tdc, code, frac, self.boundaries)
            lo = self.chip.n_max[tdc] + 1
            d2 = np.where(art, lo + np.floor(r * (256 - lo)).astype(np.int64), d2)
            words[ev.index] = encode_words(code // 8, code % 8, d2 // 8, d2 % 8, tdc)
            starts = Starts(ev.index, starts.kind, starts.t_s, starts.code)
        # class counts from the STARTs alone: every other word is a no_hit
        counts = np.zeros((N_CLASSES, n), np.int64)
        counts[HIT] = np.bincount(tdc[~art], minlength=n)
        counts[ARTIFACT] = np.bincount(tdc[art], minlength=n)
        counts[NO_HIT] = n_cycles - counts[HIT] - counts[ARTIFACT]
        if self.invalid_rate > 0 or self.malformed_rate > 0:
            self._corrupt(words, counts, ev.index, art, rng)
        return words, counts

    def _corrupt(self, words, counts, index, art, rng):
        """Corrupt a fraction of the words in place, moving their counts to the new class."""
        n = self.n_tdc
        cls = np.full(words.size, NO_HIT, np.int8)
        cls[index] = np.where(art, ARTIFACT, HIT)
        for rate, new in ((self.invalid_rate, INVALID_PHASE), (self.malformed_rate, MALFORMED)):
            if rate <= 0:
                continue
            bad = np.flatnonzero(rng.random(words.size) < rate)
            if new == INVALID_PHASE:
                bubble = BUBBLE_CODES[rng.integers(0, BUBBLE_CODES.size, bad.size)]
                words[bad] = (words[bad] & ~np.uint32(0xF << 12)) | (bubble << 12)
            else:
                bit = MARKER_BITS[rng.integers(0, MARKER_BITS.size, bad.size)]
                words[bad] ^= np.uint32(1) << bit
            np.subtract.at(counts, (cls[bad].astype(np.int64), bad % n), 1)
            np.add.at(counts, (np.full(bad.size, new), bad % n), 1)
            cls[bad] = new

    def batches(self, cycles: int) -> Iterator[tuple[int, np.ndarray]]:
        """``(first_cycle, words)`` over ``cycles`` cycles, in CHUNK_CYCLES chunks."""
        for index, start in enumerate(range(0, cycles, CHUNK_CYCLES)):
            n = min(CHUNK_CYCLES, cycles - start)
            words, counts = self.chunk(index, n)
            self.result.class_counts += counts
            self.result.cycles += n
            yield start, words

    def truth(self) -> dict:
        """The sidecar's ``truth``: what the processing stages should find."""
        sm, s, g = self.sm, self.sm.scene.sensor, self.sm.scene.gate
        from schemas.constants import WORD_CLASSES

        return {
            "generator": "tcspc-lidar simulator", "engine": self.engine_name,
            "seed": self.seed, "chunk_cycles": CHUNK_CYCLES, "scene": sm.scene.name,
            "distance_m": [None if np.isnan(d) else float(d) for d in sm.distance_m],
            "m_signal": np.round(sm.m_signal, 9).tolist(),
            "bg_rate_hz": np.round(sm.bg_rate_hz, 3).tolist(),
            "delay_ns": g.delay_ns, "t_laser_win_ns": g.t_laser_win_ns,
            "detections_per_pixel_per_cycle": self.light,
            "sigma_optical_ps": self.optics.sigma_s * 1e12,
            "reset_ns": self.optics.reset_s * 1e9 if self.chip.reset_ns is not None
            else s.reset_ns,
            "class_counts": {name: self.result.class_counts[i].tolist()
                             for i, name in enumerate(WORD_CLASSES)},
            "cycles": self.result.cycles,
            "chip": self.chip.truth(self.light, self.optics.window_s),
            "report": [e.__dict__ for e in sm.report],
        }


__all__ = ["CHUNK_CYCLES", "Simulator", "optics_from_scene", "detections_per_pixel_per_cycle"]
