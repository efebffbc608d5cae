from pathlib import Path

import numpy as np
import pytest

from stages.models.scene import SceneError, evaluate, load_scene, scene_from_dict

SCENES = Path(__file__).parents[3] / "scenes"


@pytest.mark.parametrize("name", ["short_range", "long_range", "density", "delay", "street"])
def test_shipped_scenes_load_and_evaluate(name):
    sm = evaluate(load_scene(SCENES / f"{name}.toml"))
    assert sm.m_signal.shape == (128,) and np.all(sm.m_signal >= 0)
    assert np.all(np.isfinite(sm.bg_rate_hz)) and np.all(sm.bg_rate_hz >= 0)
    assert {e.name for e in sm.report} >= {"atmosphere", "motion", "ambient", "gate"}
    has = ~np.isnan(sm.distance_m)
    assert np.all((sm.tof_in_window_s[has] >= 0) & (sm.tof_in_window_s[has] < sm.window_s))


def test_only_declared_effects_are_computed_and_small_ones_are_reported():
    base = {"targets": [{"pixels": [0, 9], "distance_m": 3.0}],
            "ambient": [{"kind": "lux", "lux": 1000.0}]}
    sm = evaluate(scene_from_dict(base))
    assert {e.name: e.status for e in sm.report}["atmosphere"] == "not declared"
    # 3 m of air changes the signal by ~1e-4: declared, but below the tolerance
    sm2 = evaluate(scene_from_dict({**base, "atmosphere": {"temperature_k": 290.0}}))
    eff = {e.name: e for e in sm2.report}["atmosphere"]
    assert eff.status == "omitted (below tolerance)" and 0 < eff.size < 1e-3
    np.testing.assert_array_equal(sm2.m_signal, sm.m_signal)
    # ... and computed when the tolerance is tighter
    sm3 = evaluate(scene_from_dict({**base, "atmosphere": {}, "tolerance": 1e-6}))
    assert {e.name: e.status for e in sm3.report}["atmosphere"] == "computed"
    assert np.all(sm3.m_signal[:10] < sm.m_signal[:10])


def test_hot_pixels_and_motion_are_reported():
    sm = evaluate(scene_from_dict({"targets": [{"pixels": [0, 3], "distance_m": 5.0,
                                                "velocity_m_s": 10.0}]}))
    eff = {e.name: e for e in sm.report}
    assert eff["motion"].status == "needs the reference engine"
    assert sm.bg_rate_hz[66] > sm.bg_rate_hz[0]  # hot pixel 67 (1-based)


@pytest.mark.parametrize("raw, message", [
    ({"targets": [{"pixels": [0, 200], "distance_m": 1.0}]},
     r"^x.toml \[\[targets\]\] #1 pixels: \[0, 200\] outside 0..127"),
    ({"targets": [{"pixels": [0, 2], "distance_m": -1.0}]},
     r"^x.toml \[\[targets\]\] #1 distance_m: must be > 0, found -1.0$"),
    ({"targets": [{"pixels": [0, 2], "distance_m": 1.0, "surface": "glass"}]},
     r"^x.toml \[\[targets\]\] #1 surface: 'glass' is not one of diffuse, mirror, specular$"),
    ({"laser": {"colour": "blue"}}, r"^x.toml \[laser\] colour: unknown key \(known: "),
    ({"gate": {"t_laser_win_ns": "abc"}},
     r"^x.toml \[gate\] t_laser_win_ns: expected a finite number, found text 'abc'$"),
    ({"sensor": {"n_pixels": 12.5}},
     r"^x.toml \[sensor\] n_pixels: expected an integer, found a number 12.5$"),
    ({"histogram": {"bins": 3}}, r"^x.toml \[histogram\]: unknown section"),
    ({"wind": 3}, r"^x.toml wind: unknown key"),
    ({"targets": [{"pixels": [0, 2]}]}, r"^x.toml \[\[targets\]\] #1 distance_m: missing"),
])
def test_bad_scenes_are_clear_errors(raw, message):
    with pytest.raises(SceneError, match=message):
        scene_from_dict(raw, "x.toml")


def test_every_problem_in_one_pass():
    raw = {"gate": {"t_laser_win_ns": "abc", "delay_ns": -1},
           "laser": {"colour": "blue", "beam_mm": [1.0]},
           "targets": [{"pixels": [0, 2], "distance_m": 1.0, "reflectivity": 2},
                       {"pixels": [5, 1], "distance_m": 3.0}],
           "ambient": [{"kind": "moon"}], "atmosphere": {"relative_humidity": "60%"},
           "tolerance": -1}
    with pytest.raises(SceneError) as info:
        scene_from_dict(raw, "x.toml")
    lines = str(info.value).splitlines()
    keys = [line.split(":")[0] for line in lines]
    assert keys == ["x.toml tolerance", "x.toml [laser] colour", "x.toml [laser] beam_mm",
                    "x.toml [gate] t_laser_win_ns", "x.toml [gate] delay_ns",
                    "x.toml [atmosphere] relative_humidity",
                    "x.toml [[targets]] #1 reflectivity", "x.toml [[targets]] #2 pixels",
                    "x.toml [[ambient]] #1 kind"]


def test_transmittance_is_a_fraction():
    from stages.models.scene import Target, check_scene

    if "transmittance" not in Target.__dataclass_fields__:
        pytest.skip("targets have no transmittance in this version of the simulator")
    ok = {"targets": [{"pixels": [0, 2], "distance_m": 1.0, "transmittance": t}
                      for t in (0, 0.3, 1.0)]}
    assert check_scene(ok, "x.toml") == []
    bad = {"targets": [{"pixels": [0, 2], "distance_m": 1.0, "transmittance": t}
                       for t in (-0.1, 1.5)]}
    assert [p.split(": ", 1)[1] for p in check_scene(bad, "x.toml")] == [
        "must be >= 0 and <= 1, found -0.1", "must be >= 0 and <= 1, found 1.5"]


def test_files_that_are_not_scenes(tmp_path):
    png = tmp_path / "street.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    with pytest.raises(SceneError, match=r"street.png: not a scene: the file is a PNG image"):
        load_scene(png)
    with pytest.raises(SceneError, match="a directory"):
        load_scene(tmp_path)


def test_missing_or_broken_file(tmp_path):
    with pytest.raises(SceneError, match="scene file not found"):
        load_scene(tmp_path / "nope.toml")
    (tmp_path / "bad.toml").write_text("name = ")
    with pytest.raises(SceneError, match="not valid TOML"):
        load_scene(tmp_path / "bad.toml")
