"""Install without make: a wheel of the repository installs into a clean virtual
environment and runs `tcspc demo` there (slow: it downloads the dependencies)."""

import json
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_wheel_installs_and_runs_the_demo(tmp_path):
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w",
                    str(tmp_path / "dist"), str(ROOT)], check=True, timeout=600)
    (wheel,) = (tmp_path / "dist").glob("tcspc_lidar-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    shipped = {f"{d}/{p.name}" for d in ("scenes", "geometries")
               for p in (ROOT / d).glob("*.toml")}
    assert shipped <= names, f"scenes missing from the wheel: {sorted(shipped - names)}"
    assert not [n for n in names if n.startswith(("tests/", "benchmarks/", "examples/"))]

    venv.create(tmp_path / "env", with_pip=True)
    bin_ = tmp_path / "env" / "bin"
    # a clean environment: no PYTHONPATH, so neither pip nor the demo sees the checkout
    env = {"PATH": f"{bin_}:/usr/bin:/bin", "HOME": str(tmp_path),
           "PREFECT_HOME": str(tmp_path / ".prefect"),
           "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
           "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "180"}
    subprocess.run([str(bin_ / "python"), "-m", "pip", "install", "-q", str(wheel)],
                   check=True, timeout=1200, env=env, cwd=tmp_path)
    run = tmp_path / "run"  # not the checkout: only the installed files are seen
    run.mkdir()
    proc = subprocess.run([str(bin_ / "tcspc"), "demo", "--out", "data"], cwd=run, env=env,
                          capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads((run / "data" / "demo.json").read_text())["ok"] is True
