"""Scenes: a TOML file declaring targets, ambient light, atmosphere, laser, sensor and gate.

"Model only what a scene needs": an effect is computed only when the scene declares it,
and a declared effect whose contribution is below ``tolerance`` (relative) is omitted; both
are reported (:attr:`SceneModel.report`) with their size and their domain of validity.

Timing. The laser fires at t = 0; a photon from a target at distance d arrives at
``delay + 2 d / c`` (``delay`` is the system delay that eq. 5.3 measures at zero distance);
the window closes at ``t_laser_win`` and opens ``window`` earlier. The TDC code is
``(t_laser_win - t_detect) / LSB``: early photons have high codes (reversed timing).
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.constants import c as C_LIGHT

from schemas.errors import TcspcError
from stages.models import atmosphere as atm
from stages.models import noise, signal
from stages.models.scene_check import check_table
from stages.models.tcspc import combined_sigma, sigma_from_fwhm


class SceneError(TcspcError, ValueError):
    """A scene file is invalid (names the file, the key and the problem)."""


@dataclass(frozen=True)
class Laser:
    wavelength_nm: float = 405.0
    energy_pj: float = 29.0
    rep_rate_hz: float = 40e6
    fwhm_ps: float = 44.8
    jitter_ps: float = 1.6
    beam_mm: tuple[float, float] = (2.5, 1.1)
    divergence_mrad: tuple[float, float] = (0.1, 0.25)


@dataclass(frozen=True)
class Sensor:
    n_pixels: int = 128
    pitch_um: float = 24.0
    fill_factor: float = 0.049
    pdp: float = 0.25
    dcr_hz: float = 100.0
    hot_pixels: tuple[int, ...] = noise.HOT_PIXELS
    hot_dcr_hz: float = 5000.0
    spad_jitter_ps: float = 178.2     # with the laser's (section 3.1)
    lsb_ps: float = 202.5             # Table 3.2: 200-205 ps
    tdc_jitter_fwhm_lsb: float = 1.2
    window_ns: float = 80.0
    reset_ns: float = 20.0            # reset period before the window (section 2.2.3)
    readout_us: float = 102.0         # one cycle (section 3.3)

    @property
    def pde(self) -> float:
        return self.pdp * self.fill_factor


@dataclass(frozen=True)
class Gate:
    t_laser_win_ns: float = 140.0
    delay_ns: float = 100.0  # system delay: eq. 5.3 measures it; the thesis prints no value


@dataclass(frozen=True)
class Atmosphere:
    temperature_k: float = 288.15
    pressure_pa: float | None = None
    altitude_m: float = 0.0
    relative_humidity: float = 0.0


@dataclass(frozen=True)
class Ambient:
    kind: str = "lux"                 # "lux" (sunlight-like), "sun" (direct, sea level), "lamp"
    lux: float = 0.0
    filter_nm: float = 10.0
    lamp_lm: float = 0.0
    lamp_distance_m: float = 10.0
    lamp_half_angle_deg: float = 90.0
    lamp_efficacy_lm_per_w: float = 100.0


@dataclass(frozen=True)
class Target:
    pixels: tuple[int, int]           # inclusive range of pixels the target covers
    distance_m: float
    reflectivity: float = 0.5
    surface: str = "diffuse"          # "diffuse", "mirror" (collimated return), "specular"
    roughness_um: float | None = None  # RMS height; decides the regime when given
    incidence_deg: float = 0.0
    velocity_m_s: float = 0.0          # range rate, positive receding
    # the fraction of the light that passes through to the targets behind it in the same
    # pixels (a window, a fence), each way; 0 = opaque. What is reflected is reflectivity.
    transmittance: float = 0.0


@dataclass(frozen=True)
class Scene:
    name: str
    laser: Laser = field(default_factory=Laser)
    sensor: Sensor = field(default_factory=Sensor)
    gate: Gate = field(default_factory=Gate)
    targets: tuple[Target, ...] = ()
    ambient: tuple[Ambient, ...] = ()
    atmosphere: Atmosphere | None = None
    dark_counts: bool = True
    tolerance: float = 1e-3


@dataclass(frozen=True)
class Effect:
    """One line of a scene's report."""

    name: str
    status: str        # "computed", "omitted (below tolerance)", "not declared"
    size: float        # relative contribution (see ``detail``)
    detail: str
    domain: str


@dataclass(frozen=True)
class SceneModel:
    """Per-pixel inputs of the TCSPC model for a scene, and the report of effects."""

    scene: Scene
    m_signal: np.ndarray       #: signal detections per cycle
    tof_in_window_s: np.ndarray  #: arrival time of the return after the window opened
    distance_m: np.ndarray     #: NaN where no target
    sigma_s: float             #: total jitter (eq. 2.18)
    bg_rate_hz: np.ndarray     #: ambient + dark detections per second
    report: tuple[Effect, ...]
    #: every surface a pixel sees, nearest first (n_pixels, K): signal detections per
    #: cycle, arrival time after the window opened and distance (0, NaN, NaN past the
    #: last); column 0 is ``m_signal``, ``tof_in_window_s``, ``distance_m``
    returns_m: np.ndarray | None = None
    returns_tof_s: np.ndarray | None = None
    returns_distance_m: np.ndarray | None = None

    @property
    def window_s(self) -> float:
        return self.scene.sensor.window_ns * 1e-9


def _build(cls, data: dict, where: str):
    known = cls.__dataclass_fields__
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise SceneError(f"{where}: unknown keys {unknown}; known: {sorted(known)}")
    try:
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})
    except TypeError as exc:
        raise SceneError(f"{where}: {exc}") from exc


#: First bytes of files people give by mistake, named in the error.
_NOT_TOML = {b"\x89PNG": "a PNG image", b"\xff\xd8\xff": "a JPEG image", b"%PDF": "a PDF",
             b"PK\x03\x04": "a zip archive", b"PQTTTR": "a PicoQuant PTU file",
             b"\x7fELF": "a program"}


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene TOML file (every problem at once: :func:`scene_from_dict`)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise SceneError(f"{path}: scene file not found") from None
    except IsADirectoryError:
        raise SceneError(f"{path}: a directory; a scene is a TOML file") from None
    try:
        raw = tomllib.loads(data.decode("utf-8"))
    except UnicodeDecodeError:
        what = next((v for k, v in _NOT_TOML.items() if data.startswith(k)), "binary data")
        raise SceneError(f"{path}: not a scene: the file is {what}, a scene is a TOML text "
                         "file (see scenes/street.toml)") from None
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{path}: not valid TOML: {exc}") from exc
    except RecursionError:  # (tomllib recurses per level of nesting)
        raise SceneError(f"{path}: arrays or tables nested too deeply to read") from None
    return scene_from_dict(raw, str(path))


_SECTIONS = {"laser": Laser, "sensor": Sensor, "gate": Gate, "atmosphere": Atmosphere}
_LISTS = {"targets": Target, "ambient": Ambient}


def check_scene(raw: dict, where: str = "scene") -> list[str]:
    """Every problem of a scene's TOML table, one line each naming ``where`` (the file),
    the section and the key; empty when the scene is valid."""
    if not isinstance(raw, dict):
        return [f"{where}: a scene is a TOML table, found {type(raw).__name__}"]
    tables = [k for k, v in raw.items() if isinstance(v, dict | list) and k not in _SECTIONS
              and k not in _LISTS]
    problems = [f"{where} [{k}]: unknown section (known: {', '.join(_SECTIONS)}, "
                f"{', '.join(f'[[{x}]]' for x in _LISTS)})" for k in tables]
    problems += check_table(Scene, raw, where, skip=("name", *_SECTIONS, *_LISTS, *tables))
    if "name" in raw and not isinstance(raw["name"], str):
        problems.append(f"{where} name: expected text in quotes, found {raw['name']!r}")
    for key, cls in _SECTIONS.items():
        if key in raw:
            problems += check_table(cls, raw[key], f"{where} [{key}]")
    sensor = raw.get("sensor")
    n_pixels = sensor.get("n_pixels") if isinstance(sensor, dict) else None
    n_pixels = n_pixels if isinstance(n_pixels, int) and n_pixels >= 1 else Sensor.n_pixels
    for key, cls in _LISTS.items():
        items = raw.get(key, [])
        if not isinstance(items, list):
            problems.append(f"{where} {key}: expected [[{key}]] tables, found {items!r}")
            continue
        for i, item in enumerate(items):
            here = f"{where} [[{key}]] #{i + 1}"
            found = check_table(cls, item, here)
            problems += found
            px = item.get("pixels") if isinstance(item, dict) else None
            if key == "targets" and px is not None and \
                    not any(p.startswith(f"{here} pixels:") for p in found) and \
                    not 0 <= px[0] <= px[1] < n_pixels:
                problems.append(f"{here} pixels: {list(px)} outside 0..{n_pixels - 1} "
                                "(first <= last)")
    return problems


def scene_from_dict(raw: dict, where: str = "scene") -> Scene:
    """A :class:`Scene` from a scene's TOML table; :class:`SceneError` lists every problem,
    one line each, before anything is built."""
    problems = check_scene(raw, where)
    if problems:
        raise SceneError("\n".join(problems))
    raw = dict(raw)
    kw = {"name": str(raw.pop("name", Path(where).stem))}
    for key, cls in (("laser", Laser), ("sensor", Sensor), ("gate", Gate)):
        if key in raw:
            kw[key] = _build(cls, raw.pop(key), f"{where} [{key}]")
    if "atmosphere" in raw:
        kw["atmosphere"] = _build(Atmosphere, raw.pop("atmosphere"), f"{where} [atmosphere]")
    kw["targets"] = tuple(_build(Target, t, f"{where} [[targets]] #{i + 1}")
                          for i, t in enumerate(raw.pop("targets", [])))
    kw["ambient"] = tuple(_build(Ambient, a, f"{where} [[ambient]] #{i + 1}")
                          for i, a in enumerate(raw.pop("ambient", [])))
    for key in ("dark_counts", "tolerance"):
        if key in raw:
            kw[key] = raw.pop(key)
    if raw:
        raise SceneError(f"{where}: unknown top-level keys {sorted(raw)}")
    scene = Scene(**kw)
    _validate(scene, where)
    return scene


def _validate(scene: Scene, where: str) -> None:
    n = scene.sensor.n_pixels
    for i, t in enumerate(scene.targets):
        lo, hi = t.pixels
        if not 0 <= lo <= hi < n:
            raise SceneError(f"{where}: target #{i + 1} pixels {t.pixels} outside 0..{n - 1}")
        if not t.distance_m > 0:
            raise SceneError(f"{where}: target #{i + 1} distance_m must be > 0")
        if not 0 <= t.reflectivity <= 1:
            raise SceneError(f"{where}: target #{i + 1} reflectivity must be in [0, 1]")
        if not 0 <= t.transmittance <= 1:
            raise SceneError(f"{where}: target #{i + 1} transmittance must be in [0, 1]")
        if t.surface not in ("diffuse", "mirror", "specular"):
            raise SceneError(f"{where}: target #{i + 1} surface {t.surface!r}: use diffuse, "
                             "mirror or specular")
    for i, a in enumerate(scene.ambient):
        if a.kind not in ("lux", "sun", "lamp"):
            raise SceneError(f"{where}: ambient #{i + 1} kind {a.kind!r}: use lux, sun or lamp")
    if not 0 < scene.gate.t_laser_win_ns:
        raise SceneError(f"{where}: gate t_laser_win_ns must be > 0")


def evaluate(scene: Scene, cycles: int = 40_000) -> SceneModel:
    """Per-pixel model inputs for ``cycles`` cycles of the scene, with the effects report."""
    s, las, g = scene.sensor, scene.laser, scene.gate
    n = s.n_pixels
    lam = las.wavelength_nm * 1e-9
    pitch = s.pitch_um * 1e-6
    report: list[Effect] = []
    tol = scene.tolerance
    m = np.zeros(n)
    dist = np.full(n, np.nan)
    tof = np.full(n, np.nan)
    window_open_s = (g.t_laser_win_ns - s.window_ns) * 1e-9
    sigma = float(combined_sigma(sigma_from_fwhm(las.fwhm_ps * 1e-12), las.jitter_ps * 1e-12,
                                 s.spad_jitter_ps * 1e-12,
                                 sigma_from_fwhm(s.tdc_jitter_fwhm_lsb * s.lsb_ps * 1e-12)))
    beam = dict(beam_major_m=las.beam_mm[0] * 1e-3, beam_minor_m=las.beam_mm[1] * 1e-3,
                div_major_rad=las.divergence_mrad[0] * 1e-3,
                div_minor_rad=las.divergence_mrad[1] * 1e-3)
    energy = las.energy_pj * 1e-12
    capture_s = cycles * s.readout_us * 1e-6
    atm_sizes, motion_sizes = [], []
    surfaces = []  # (slice, m, tof, distance, transmittance) of each target
    for t in scene.targets:
        sl = slice(t.pixels[0], t.pixels[1] + 1)
        surface = t.surface
        if t.roughness_um is not None:
            surface = ("specular" if signal.surface_regime(t.roughness_um * 1e-6, lam)
                       == "specular" and surface != "mirror" else surface)
        if surface == "diffuse":
            n_ph = signal.diffuse_photons_per_pixel(t.distance_m, t.reflectivity, energy, lam,
                                                    pitch)
        elif surface == "mirror":
            n_ph = signal.collimated_photons_per_pixel(2 * t.distance_m, energy, lam, pitch,
                                                       **beam) * t.reflectivity
        else:
            n_ph = signal.specular_photons_per_pixel(t.distance_m, t.reflectivity,
                                                     np.radians(t.incidence_deg), energy,
                                                     lam, pitch, **beam)
        trans = 1.0
        if scene.atmosphere is not None:
            a = scene.atmosphere
            if a.altitude_m > 0:
                tr = atm.transmission_at_altitude(2 * t.distance_m, a.altitude_m,
                                                  a.temperature_k, a.relative_humidity)
            else:
                tr = atm.transmission(2 * t.distance_m, a.pressure_pa or atm.P_SEA_LEVEL_PA,
                                      a.temperature_k)
            atm_sizes.append(1 - float(tr))
            if 1 - float(tr) >= tol:
                trans = float(tr)
        surfaces.append((sl, float(signal.signal_detections_per_cycle(n_ph, s.pdp,
                                                                       s.fill_factor, trans)),
                         g.delay_ns * 1e-9 + 2 * t.distance_m / C_LIGHT - window_open_s,
                         t.distance_m, t.transmittance))
        motion_sizes.append(2 * abs(t.velocity_m_s) * capture_s / C_LIGHT / sigma)
    r_m, r_tof, r_dist = _returns(n, surfaces)
    m, tof, dist = r_m[:, 0].copy(), r_tof[:, 0].copy(), r_dist[:, 0].copy()
    if scene.atmosphere is None:
        report.append(Effect("atmosphere", "not declared", 0.0, "no attenuation",
                             "Rayleigh only (atmosphere.py)"))
    else:
        worst = max(atm_sizes, default=0.0)
        report.append(Effect("atmosphere", "computed" if worst >= tol else
                             "omitted (below tolerance)", worst,
                             f"largest round-trip loss {worst:.2e}",
                             "Rayleigh scattering, clear air"))
    worst_motion = max(motion_sizes, default=0.0)
    if any(t.velocity_m_s for t in scene.targets):
        report.append(Effect("motion", "needs the reference engine" if worst_motion >= tol
                             else "omitted (below tolerance)", worst_motion,
                             f"TOF drift over {cycles} cycles / jitter = {worst_motion:.2e}",
                             "constant range rate"))
    else:
        report.append(Effect("motion", "not declared", 0.0, "static targets", "-"))
    # background
    amb_hz = 0.0
    for a in scene.ambient:
        if a.kind == "lux":
            e = noise.lux_to_spectral_irradiance(a.lux, lam)
        elif a.kind == "sun":
            e = noise.solar_irradiance_sea_level(lam) * 1e-9
        else:
            lux = noise.lamp_illuminance_lux(a.lamp_lm, a.lamp_distance_m,
                                             a.lamp_half_angle_deg)
            e = noise.lamp_band_irradiance_w_m2(lux, a.lamp_efficacy_lm_per_w) / 10.0
        amb_hz += float(noise.photon_rate_hz(e, a.filter_nm, pitch ** 2, lam)) * s.pde
    bg = np.full(n, amb_hz)
    report.append(Effect("ambient", "computed" if scene.ambient else "not declared",
                         amb_hz * s.window_ns * 1e-9, "background detections per window",
                         "blackbody-shaped daylight / cone lamps, ideal filter"))
    if scene.dark_counts:
        dcr = noise.dark_count_rates_hz(n, s.dcr_hz, s.hot_pixels, s.hot_dcr_hz)
        rel = float(np.max(dcr) / amb_hz) if amb_hz > 0 else float("inf")
        if rel >= tol:
            bg = bg + dcr
            # (no ambient light: the ratio is infinite; the rate itself says more)
            size, what = ((rel, "largest DCR / ambient rate") if amb_hz > 0 else
                          (float(np.max(dcr)), "largest DCR in Hz, no ambient light"))
            report.append(Effect("dark counts", "computed", size, what,
                                 "Table 3.1 with hot pixels"))
        else:
            report.append(Effect("dark counts", "omitted (below tolerance)", rel,
                                 "largest DCR / ambient rate", "Table 3.1 with hot pixels"))
    inside = (tof >= 0) & (tof < s.window_ns * 1e-9)
    report.append(Effect("gate", "computed", float(np.mean(~inside[~np.isnan(dist)]))
                         if np.any(~np.isnan(dist)) else 0.0,
                         "fraction of target pixels whose return is outside the window",
                         "returns outside the window are not seen"))
    return SceneModel(scene, m, tof, dist, sigma, bg, tuple(report), r_m, r_tof, r_dist)


def _returns(n: int, surfaces) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel, the surfaces it sees nearest first (n, K): a surface's signal is scaled by
    the squared transmittance of every surface before it (the light passes each way), and
    an opaque one hides what is behind it. K is the most any pixel sees (at least 1)."""
    per = [[] for _ in range(n)]
    for sl, m, tof, d, tr in surfaces:
        for p in range(n)[sl]:
            per[p].append((d, m, tof, tr))
    k = max([1] + [len(v) for v in per])
    r_m, r_tof, r_d = np.zeros((n, k)), np.full((n, k), np.nan), np.full((n, k), np.nan)
    for p, v in enumerate(per):
        through = 1.0
        for j, (d, m, tof, tr) in enumerate(sorted(v)):
            if through <= 0:
                break
            r_m[p, j], r_tof[p, j], r_d[p, j] = m * through, tof, d
            through *= tr * tr
    return r_m, r_tof, r_d
