import json
from pathlib import Path

import polars as pl
import pytest
from click.testing import CliRunner

from pipeline.cli.app import cli

SCENES = Path(__file__).parents[3] / "scenes"


def run(*args):
    res = CliRunner().invoke(cli, ["model", *args])
    assert res.exit_code == 0, res.output
    return res.stdout


def test_link_budget_json_has_eq_2_23():
    rows = json.loads(run("link-budget", "-d", "100", "--json"))
    assert abs(rows[0]["collimated_at_d"] - 9.4) < 0.05


def test_ambient_transmission_and_table_2_2():
    assert "sea level" in run("ambient")
    rows = json.loads(run("transmission", "-d", "200", "--temperature", "273", "--json"))
    assert abs(rows[0]["transmission"] - 0.9914) < 1e-4
    assert len(json.loads(run("table", "--json"))) == 8


def test_ambient_daylight_is_the_thesis_number():
    """Section 2.2.2: 100 klx through a 10 nm filter on a 24 um pixel is 1.0 W/m^2/nm and
    1.17e10 photons/s; a scene's `kind = "lux"` ambient uses the same conversion."""
    from stages.models.scene import evaluate, scene_from_dict

    rows = json.loads(run("ambient", "--lux", "100000", "--json"))
    day = next(r for r in rows if "daylight" in r["source"])
    assert day["w_m2_nm"] == 1.0
    assert round(day["photons_hz"] / 1e10, 2) == 1.17
    scene = scene_from_dict({"ambient": [{"kind": "lux", "lux": 1e5, "filter_nm": 10.0}],
                             "dark_counts": False}, "day.toml")
    pde = scene.sensor.pde
    assert evaluate(scene).bg_rate_hz[0] / pde == pytest.approx(day["photons_hz"], rel=1e-12)


def test_predict_writes_parquet_and_plot(tmp_path):
    out, png = tmp_path / "p.parquet", tmp_path / "p.png"
    rows = json.loads(run("predict", "-c", "1", "-d", "5", "--json", "--out", str(out),
                          "--plot", str(png)))
    assert rows[0]["config"] == 1 and 0 <= rows[0]["5 m"] <= 1
    df = pl.read_parquet(out)
    assert set(df["config"].unique()) == set(range(1, 9))
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_histogram_of_a_scene(tmp_path):
    rows = json.loads(run("histogram", str(SCENES / "street.toml"), "--json", "--plot",
                          str(tmp_path / "h.png")))
    assert rows[0]["crlb_mm"] > 0 and rows[0]["peak_count"] > 0


def test_figures(tmp_path):
    listed = run("figures", "--out", str(tmp_path)).split()
    assert len(listed) == 4 and all(Path(p).read_bytes()[:4] == b"\x89PNG" for p in listed)
