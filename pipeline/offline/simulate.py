"""Simulated captures: a scene file in, ``NAME.bin`` + ``NAME.json`` (with truth) out."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from pipeline.io.capture import Capture, CaptureMeta, CaptureWriter
from stages.models.scene import Scene, evaluate, load_scene
from stages.simulator.chip import Chip, make_chip
from stages.simulator.source import Simulator


def make_simulator(scene_path, cycles: int, seed: int = 0, chip_seed: int = 1,
                   engine: str | None = None, malformed_rate: float = 0.0,
                   invalid_rate: float = 0.0, ideal_tdc: bool = False,
                   chip: Chip | None = None) -> Simulator:
    """A simulator for a scene file (or a :class:`Scene`); the engine defaults to the
    reference one only for scenes that need it (a moving target, a surface behind a
    partially transparent one). ``chip``: a chip of
    one's own (the zoo's, :func:`stages.simulator.chip.random_chip`) instead of
    ``make_chip(n_pixels, chip_seed)``."""
    scene = scene_path if isinstance(scene_path, Scene) else load_scene(scene_path)
    sm = evaluate(scene, cycles)
    moving = any(t.velocity_m_s for t in sm.scene.targets)
    layered = sm.returns_m is not None and bool((sm.returns_m[:, 1:] > 0).any())
    engine = engine or ("reference" if moving or layered else "fast")
    if chip is None:
        chip = make_chip(sm.scene.sensor.n_pixels, chip_seed,
                         **({"inl_scale": 0.0, "artifact_rate": 0.0} if ideal_tdc else {}))
    return Simulator(sm, chip, seed, engine, malformed_rate, invalid_rate)


def capture_kind(scene) -> str:
    """The sidecar's ``kind`` (docs/design.md): density without a target, delay when every target
    sits at zero distance (under 5 cm), else range."""
    if not scene.targets:
        return "density"
    if all(t.distance_m < 0.05 for t in scene.targets):
        return "delay"
    return "range"


def _scene_name(scene) -> str:
    return f"scene {scene.name!r}" if isinstance(scene, Scene) else Path(scene).name


def simulate_capture(scene_path, cycles: int, out, progress: Callable[[int], None] = None,
                     **kw) -> tuple[CaptureMeta, Simulator]:
    """Write a capture of ``cycles`` cycles of the scene; returns its sidecar and the
    simulator (whose ``result`` holds the class counts it emitted)."""
    sim = make_simulator(scene_path, cycles, **kw)
    s = sim.sm.scene
    kind = capture_kind(s)
    with CaptureWriter(out, sim.n_tdc, window_ns=s.sensor.window_ns,
                       t_laser_win_ns=s.gate.t_laser_win_ns, kind=kind,
                       note=f"simulated from {_scene_name(scene_path)}") as w:
        for _, words in sim.batches(cycles):
            w.write(words)
            if progress:
                progress(words.size // sim.n_tdc)
        w.set_truth(sim.truth())
    return Capture(out, strict=True).meta, sim


class SimulatedCapture:
    """A simulated capture read like one, without writing it: ``meta``, ``name``,
    ``bin_path`` (a label), ``paths`` (none: nothing to hash), ``truth`` and
    ``iter_chunks()`` over exactly the words ``simulate_capture`` would write. Each pass
    regenerates them (the simulator is deterministic per chunk), so a calibration that
    needs 1e8 cycles of a density test costs time, not 3 GB of disk per 8 TDCs."""

    def __init__(self, scene_path, cycles: int, name: str | None = None, **kw):
        self.sim = make_simulator(scene_path, cycles, **kw)
        s = self.sim.sm.scene
        self.name = name or s.name
        self.cycles = cycles
        self.n_words = cycles * self.sim.n_tdc
        self.bin_path = Path(f"<simulated {self.name}>")
        self.paths: list[Path] = []
        self.meta = CaptureMeta.from_dict(
            {"format": "tcspc-raw", "version": 1, "n_tdc": self.sim.n_tdc,
             "window_ns": s.sensor.window_ns, "t_laser_win_ns": s.gate.t_laser_win_ns,
             "cycles": cycles, "kind": capture_kind(s)}, self.name)

    @property
    def truth(self) -> dict:
        return self.sim.truth()

    def iter_chunks(self, chunk_words: int | None = None):
        n = self.sim.n_tdc
        for first_cycle, words in self.sim.batches(self.cycles):
            yield first_cycle * n, words


#: the tests' calibration campaign (tests/conftest.py ``caldir``): four density tests of
#: 300 000 cycles at these lux (the range's light falls between them) and a zero-distance
#: capture of 150 000 cycles
CAMPAIGN_LUX = (133.950, 535.799, 1607.398, 4018.495)


def simulated_calibration(d, n_tdc: int, chip: Chip | None = None, seed: int = 0) -> Path:
    """A calibration directory (``d``/cal) of a simulated ``n_tdc``-TDC chip (the
    simulator's default one, or ``chip``, e.g. the zoo's): LSB against light from four
    density tests and a delay from a zero-distance capture, built as `tcspc calibrate lsb`
    and `calibrate delay` build it (``inl_rms_lsb`` 1). ``seed`` > 0 draws other captures
    (the chip calibrated again: other fixed errors a TDC)."""
    from pipeline.offline.calibrate import add_delay, lsb_campaign
    from stages.models.scene import scene_from_dict

    d = Path(d)
    kw = {} if chip is None else {"chip": chip}
    caps = []
    for i, lux in enumerate(CAMPAIGN_LUX):
        dens = scene_from_dict({"name": f"d{i}", "sensor": {"n_pixels": n_tdc},
                                "ambient": [{"kind": "lux", "lux": lux}]})
        simulate_capture(dens, 300_000, d / f"d{i}", seed=3 + i + 10 * seed, **kw)
        caps.append(d / f"d{i}")
    delay = scene_from_dict({"name": "z", "sensor": {"n_pixels": n_tdc},
                             "targets": [{"pixels": [0, n_tdc - 1], "distance_m": 0.001,
                                          "reflectivity": 0.0005, "surface": "mirror"}]})
    simulate_capture(delay, 150_000, d / "delay", seed=9 + 10 * seed, **kw)
    lsb_campaign(caps, d / "cal", inl_rms_lsb=1.0)
    add_delay(d / "delay", d / "cal")
    return d / "cal"
