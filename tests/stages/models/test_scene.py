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
    ({"targets": [{"pixels": [0, 200], "distance_m": 1.0}]}, "outside 0..127"),
    ({"targets": [{"pixels": [0, 2], "distance_m": -1.0}]}, "distance_m must be > 0"),
    ({"targets": [{"pixels": [0, 2], "distance_m": 1.0, "surface": "glass"}]}, "surface"),
    ({"laser": {"colour": "blue"}}, r"\[laser\]: unknown keys \['colour'\]"),
    ({"wind": 3}, "unknown top-level keys"),
])
def test_bad_scenes_are_clear_errors(raw, message):
    with pytest.raises(SceneError, match=message):
        scene_from_dict(raw, "x.toml")


def test_missing_or_broken_file(tmp_path):
    with pytest.raises(SceneError, match="scene file not found"):
        load_scene(tmp_path / "nope.toml")
    (tmp_path / "bad.toml").write_text("name = ")
    with pytest.raises(SceneError, match="not valid TOML"):
        load_scene(tmp_path / "bad.toml")
