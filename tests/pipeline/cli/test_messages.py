"""Messages that misled a new user (issue 37 point 5), each held: what a wrong CAPTURE is,
the short helps, `flow list`, -q, the simulator's report, view.url, the Photon-HDF5 export."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

ROOT = Path(__file__).parents[3]
T3 = ROOT / "tests" / "data" / "picoquant" / "hydraharp_v20_t3.ptu"


def tcspc(*args):
    from pipeline.cli.app import cli

    return CliRunner().invoke(cli, [str(a) for a in args])


@pytest.mark.parametrize("make, said", [
    (lambda d: d / "a_dir", "a directory; give a file"),
    (lambda d: d / "empty.parquet", "an empty file (0 bytes)"),
    (lambda d: d / "h.parquet", "a parquet file; this command takes"),
    (lambda d: d / "pic.png", "give --format tcspc|ptu|linospad2"),
])
@pytest.mark.parametrize("cmd", ["histogram", "decode"])
def test_a_wrong_capture_is_said_by_what_it_is(tmp_path, make, said, cmd):
    (tmp_path / "a_dir").mkdir()
    (tmp_path / "empty.parquet").write_bytes(b"")
    (tmp_path / "h.parquet").write_bytes(b"PAR1" + bytes(64) + b"PAR1")
    (tmp_path / "pic.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    res = tcspc(cmd, make(tmp_path), "--out", tmp_path / "o.parquet")
    assert res.exit_code == 2 and said in res.output, res.output
    if "--format" not in said:  # (a choice --format does not have is never suggested)
        assert "--format" not in res.output


def test_no_short_help_is_cut_inside_a_parenthesis():
    """click cuts a short help at the first '. ': "(eq. 5.3)" left "(eq." in a listing."""
    import click

    from pipeline.cli.app import cli
    from pipeline.cli.docs import _walk

    root = click.Context(cli, info_name="tcspc")
    for path, cmd, ctx in _walk(cli, root, ["tcspc"]):
        if not isinstance(cmd, click.Group):
            continue
        for name in cmd.list_commands(ctx):
            short = cmd.get_command(ctx, name).get_short_help_str(limit=200)
            assert short.count("(") == short.count(")") and not short.endswith("eq."), \
                f"{' '.join(path)} {name}: {short!r}"


def test_flow_list_shows_whole_sentences_without_markup():
    res = tcspc("flow", "list")
    assert res.exit_code == 0, res.output
    assert "``" not in res.output and ":func:" not in res.output
    campaign = res.output.split("calibration_campaign:", 1)[1].split("\n    ")[0]
    assert "publish to out/current" in " ".join(campaign.split())  # (its line was cut here)


def test_quiet_ranging_prints_no_response_line(tmp_path):
    res = tcspc("range", T3, "--delay-ps", "31300", "--out", tmp_path / "r.parquet", "-q")
    assert res.exit_code == 0, res.output
    assert "time axis" not in res.output and "wrote" not in res.output
    res = tcspc("range", T3, "--delay-ps", "31300", "--out", tmp_path / "r.parquet",
                "--overwrite")
    assert "time axis" in res.output  # (said without -q)


def test_a_scene_without_ambient_light_reports_no_infinite_ratio():
    from stages.models.scene import evaluate, load_scene

    sm = evaluate(load_scene(ROOT / "examples" / "zero.toml"), 1000)
    dark = [e for e in sm.report if e.name == "dark counts"]
    assert dark and all(e.size < float("inf") for e in sm.report)
    assert "no ambient light" in dark[0].detail and dark[0].size == 5000.0  # hot pixels


def test_view_url_is_removed_when_the_page_stops(tmp_path):
    state = tmp_path / "state"
    state.mkdir()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "view", "--state", state,
                             "--out", tmp_path / "out", "--port", "0", "--nice", "0"],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.time() + 60
        while not (state / "view.url").exists():
            assert proc.poll() is None, proc.stderr.read().decode()
            assert time.time() < deadline, "the page never started"
            time.sleep(0.1)
        assert re.match(r"http://127\.0\.0\.1:\d+/", (state / "view.url").read_text())
    finally:
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=20)
    assert code == 0, proc.stderr.read().decode()
    assert not (state / "view.url").exists()



LINO = ROOT / "tests" / "data" / "linospad2" / "test_data_2212b.dat"


@pytest.mark.skipif(not LINO.exists() or not T3.exists(), reason="no real sample files")
def test_spatial_says_what_an_input_it_cannot_range_is(tmp_path):
    """`range --spatial` on anything but generic histograms: one line naming the file and
    what it is, exit 2 (a LinoSPAD2 capture was "Parquet magic bytes not found")."""
    fine = tmp_path / "fine.parquet"
    assert tcspc("histogram", LINO, "--by", "pixel", "--out", fine, "-q").exit_code == 0
    for path, said in ((LINO, "a LinoSPAD2 raw capture"), (T3, "a PicoQuant PTU file"),
                       (fine, "LinoSPAD2 fine-code histograms")):
        res = tcspc("range", path, "--spatial", "--geometry", "linospad2", "--delay-ps", "0",
                    "--irf-ps", "42.5", "--out", tmp_path / "r.parquet")
        assert res.exit_code == 2, res.output
        assert said in res.output and "generic histograms" in res.output, res.output
        assert "Parquet" not in res.output and "Traceback" not in res.output
        assert not (tmp_path / "r.parquet").exists()


def test_a_range_without_a_detection_says_so_not_nan(tmp_path):
    import numpy as np
    import polars as pl

    h = tmp_path / "h.parquet"
    counts = np.random.default_rng(3).poisson(0.5, (4, 64))
    pl.DataFrame({"measurement": "m", "tdc": np.arange(4), "counts": counts.tolist(),
                  "cycles": None, "instrument": "generic", "bin_width_ps": 80.0,
                  "row": 0, "col": np.arange(4)}).write_parquet(h)
    for spatial in ((), ("--spatial",)):
        res = tcspc("range", h, "--delay-ps", "0", "--irf-ps", "40", "--p-fa", "1e-9",
                    *spatial, "--out", tmp_path / "r.parquet", "--overwrite")
        assert res.exit_code == 0, res.output
        assert "0 of 4" in res.output and "no return detected" in res.output, res.output
        assert "nan" not in res.output
