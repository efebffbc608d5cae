"""The scene file's schema check: every problem of a scene in one pass, one line each.

The scene's dataclasses (:mod:`stages.models.scene`) are the schema: a key is known when
the dataclass has the field, its type is the field's annotation, and :data:`RANGES` and
:data:`CHOICES` say which values are allowed. Each problem is one line naming the file,
the section and the key (``street.toml [gate] t_laser_win_ns: expected a number, found
'abc'``); the caller raises them all at once, before anything runs. Standard library only
(docs/decisions.md says why not pydantic).
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing

POSITIVE = (0, None, False, False)
NON_NEGATIVE = (0, None, True, False)
FRACTION = (0, 1, True, True)

#: Allowed values of the numeric keys: (low, high, low included, high included); None is
#: unbounded. Keyed by "Class.field"; a field the class does not have is not checked.
RANGES: dict[str, tuple[float | None, float | None, bool, bool]] = {
    "Laser.wavelength_nm": POSITIVE,
    "Laser.energy_pj": NON_NEGATIVE,
    "Laser.rep_rate_hz": POSITIVE,
    "Laser.fwhm_ps": NON_NEGATIVE,
    "Laser.jitter_ps": NON_NEGATIVE,
    "Laser.beam_mm": POSITIVE,
    "Laser.divergence_mrad": NON_NEGATIVE,
    "Sensor.n_pixels": (1, 256, True, True),
    "Sensor.pitch_um": POSITIVE,
    "Sensor.fill_factor": (0, 1, False, True),
    "Sensor.pdp": FRACTION,
    "Sensor.dcr_hz": NON_NEGATIVE,
    "Sensor.hot_pixels": NON_NEGATIVE,
    "Sensor.hot_dcr_hz": NON_NEGATIVE,
    "Sensor.spad_jitter_ps": NON_NEGATIVE,
    "Sensor.lsb_ps": POSITIVE,
    "Sensor.tdc_jitter_fwhm_lsb": NON_NEGATIVE,
    "Sensor.window_ns": POSITIVE,
    "Sensor.reset_ns": NON_NEGATIVE,
    "Sensor.readout_us": POSITIVE,
    "Gate.t_laser_win_ns": POSITIVE,
    "Gate.delay_ns": NON_NEGATIVE,
    "Atmosphere.temperature_k": POSITIVE,
    "Atmosphere.pressure_pa": POSITIVE,
    "Atmosphere.relative_humidity": FRACTION,
    "Ambient.lux": NON_NEGATIVE,
    "Ambient.filter_nm": POSITIVE,
    "Ambient.lamp_lm": NON_NEGATIVE,
    "Ambient.lamp_distance_m": POSITIVE,
    "Ambient.lamp_half_angle_deg": (0, 90, False, True),
    "Ambient.lamp_efficacy_lm_per_w": POSITIVE,
    "Target.pixels": NON_NEGATIVE,
    "Target.distance_m": POSITIVE,
    "Target.reflectivity": FRACTION,
    "Target.roughness_um": NON_NEGATIVE,
    "Target.incidence_deg": (0, 90, True, False),
    # the fraction of light passing through to targets behind, in the same pixels (0: opaque)
    "Target.transmittance": FRACTION,
    "Scene.tolerance": (0, 1, True, False),
}

#: Allowed values of the text keys.
CHOICES: dict[str, tuple[str, ...]] = {
    "Ambient.kind": ("lux", "sun", "lamp"),
    "Target.surface": ("diffuse", "mirror", "specular"),
}


def _describe(value) -> str:
    kind = {bool: "a boolean", str: "text", int: "an integer", float: "a number",
            dict: "a table", list: "a list"}.get(type(value), type(value).__name__)
    shown = repr(value)
    return f"{kind} {shown if len(shown) <= 40 else shown[:37] + '...'}"


def _scalar_ok(value, hint) -> str | None:
    """None when ``value`` is of type ``hint`` (a TOML value), else what was expected."""
    if hint is float:
        ok = (isinstance(value, int | float) and not isinstance(value, bool)
              and math.isfinite(value))
        return None if ok else "a finite number"
    if hint is int:
        return None if isinstance(value, int) and not isinstance(value, bool) else "an integer"
    if hint is bool:
        return None if isinstance(value, bool) else "true or false"
    if hint is str:
        return None if isinstance(value, str) else "text in quotes"
    return None


def _type_problem(value, hint) -> str | None:
    """What ``hint`` expects when ``value`` does not fit it (None when it fits)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):  # X | None: TOML has no None
        hint = next(a for a in args if a is not type(None))
        origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is tuple:
        item = args[0]
        n = None if len(args) == 2 and args[1] is Ellipsis else len(args)
        want = (f"a list of {n} {'numbers' if item is float else 'integers'}" if n else
                f"a list of {'numbers' if item is float else 'integers'}")
        if not isinstance(value, list | tuple) or (n is not None and len(value) != n):
            return want
        return want if any(_scalar_ok(v, item) for v in value) else None
    return _scalar_ok(value, hint)


def _in_range(value, spec) -> str | None:
    lo, hi, lo_in, hi_in = spec
    values = value if isinstance(value, list | tuple) else [value]
    for v in values:
        if (lo is not None and (v < lo or (v == lo and not lo_in))) or \
                (hi is not None and (v > hi or (v == hi and not hi_in))):
            low = "" if lo is None else f"{'>=' if lo_in else '>'} {lo:g}"
            high = "" if hi is None else f"{'<=' if hi_in else '<'} {hi:g}"
            return f"must be {' and '.join(x for x in (low, high) if x)}, found {value!r}"
    return None


def check_table(cls, data, where: str, skip: tuple[str, ...] = ()) -> list[str]:
    """Every problem of the TOML table ``data`` read as dataclass ``cls`` (one line each,
    starting with ``where``). Keys in ``skip`` are the caller's (sub-tables)."""
    if not isinstance(data, dict):
        return [f"{where}: expected a table, found {_describe(data)}"]
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    problems = []
    for key, value in data.items():
        if key in skip:
            continue
        if key not in fields:
            known = ", ".join(k for k in fields if k not in skip)
            problems.append(f"{where} {key}: unknown key (known: {known})")
            continue
        want = _type_problem(value, hints[key])
        if want:
            problems.append(f"{where} {key}: expected {want}, found {_describe(value)}")
            continue
        name = f"{cls.__name__}.{key}"
        if name in CHOICES and value not in CHOICES[name]:
            problems.append(f"{where} {key}: {value!r} is not one of "
                            f"{', '.join(CHOICES[name])}")
        elif name in RANGES and (bad := _in_range(value, RANGES[name])):
            problems.append(f"{where} {key}: {bad}")
    missing = [k for k, f in fields.items() if k not in skip and k not in data
               and f.default is dataclasses.MISSING
               and f.default_factory is dataclasses.MISSING]
    problems += [f"{where} {k}: missing (required)" for k in missing]
    return problems
