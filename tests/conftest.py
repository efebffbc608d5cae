import fcntl
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, settings

# Prefect: no telemetry, and a throw-away home so tests never touch the user's profile.
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")

# Property tests check correctness, not wall time: no deadline, and no health check on
# how fast inputs are drawn (a loaded 2-core machine failed test_message_roundtrip's:
# 5 inputs in 1.6 s). A test's own @settings still sets its examples.
settings.register_profile("project", deadline=None,
                          suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("project")

ENGINES = ["numpy", "numba"]


@pytest.fixture(params=ENGINES)
def engine(request):
    """Every data-path test runs on both engines, so they cannot drift apart."""
    return request.param


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def built_once(tmp_path_factory, name: str, build) -> Path:
    """The directory ``build(d)`` fills, built once a test run: with pytest-xdist by the
    first worker that asks, the others waiting for it and reading it (the workers' base
    temporary directories share their parent). Its users only read it."""
    if "PYTEST_XDIST_WORKER" not in os.environ:
        d = tmp_path_factory.mktemp(name)
        build(d)
        return d
    root = tmp_path_factory.getbasetemp().parent
    d = root / name
    with open(root / f"{name}.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # (released when the file is closed)
        if not (d / ".built").exists():
            shutil.rmtree(d, ignore_errors=True)
            d.mkdir()
            build(d)
            (d / ".built").touch()
    return d


@pytest.fixture(scope="session")
def caldir(tmp_path_factory):
    """A calibration of the 16-pixel chip of scenes/small16.toml, built once for the
    daemon's and the view's tests: LSB against light from four density tests (the range's
    light differs from any one test's), and a delay."""
    from pipeline.offline.simulate import simulated_calibration

    return built_once(tmp_path_factory, "caldir", lambda d: simulated_calibration(d, 16)) / "cal"


@pytest.fixture(scope="session")
def zoo(tmp_path_factory):
    """A chip of the zoo, not the simulator's default one (``random_chip(2, 16, ...)``: a
    real chip's random DNL and INL bow, LSB 198 ps at no light and +51 ps with light, the
    chip sweep's LSB saturation; benchmarks/spatial_chip.py --zoo 2), calibrated as
    ``caldir`` is, and a 3 x 5 grid geometry (TDCs 0..14 placed, row = tdc // 5; TDC 15
    without a pixel): ``(chip, calibration directory, geometry file)``."""
    from pipeline.offline.simulate import simulated_calibration
    from stages.simulator.chip import REAL_CHIP_RANGES, random_chip

    chip, _ = random_chip(2, 16, {**REAL_CHIP_RANGES, "n_sat": (0.5, 1.5),
                                  "artifact_rate": (0.0, 6e-4)})

    def build(d):
        simulated_calibration(d, 16, chip)
        (d / "grid.toml").write_text('name = "grid3x5"\n[grid]\nrows = 3\ncols = 5\n'
                                     'fov_h_deg = 12.0\nfov_v_deg = 7.0\n')

    d = built_once(tmp_path_factory, "zoo", build)
    return chip, d / "cal", d / "grid.toml"


@pytest.fixture(scope="session")
def mirror16():
    """A simulated measurement (20,000 cycles) of scenes/small16.toml's chip and mirror at
    1.5 m, brighter (reflectivity 0.004): the return counts more than the reset peak on
    most TDCs. ``(HistogramState, the chip's true LSB at its light, window_s)``."""
    from stages import calibration as cal
    from stages.histogram import HistogramAccumulator
    from stages.models.scene import evaluate, scene_from_dict
    from stages.simulator.chip import make_chip
    from stages.simulator.source import Simulator

    n = 16
    raw = {"sensor": {"n_pixels": n}, "gate": {"t_laser_win_ns": 140.0, "delay_ns": 100.0},
           "targets": [{"pixels": [0, n - 1], "distance_m": 1.5, "surface": "mirror",
                        "reflectivity": 0.004}],
           "ambient": [{"kind": "lux", "lux": 800.0}]}
    sm = evaluate(scene_from_dict(raw))
    chip = make_chip(n, 1)
    sim = Simulator(sm, chip, 0)
    acc = HistogramAccumulator(n, cal.SecondStage(chip.n_min, chip.n_max, chip.n_th,
                                                  chip.pdm).bounds)
    for _, w in sim.batches(20_000):
        acc.update(w)
    st = acc.snapshot()
    return st, chip.window_truth(sim.light, sm.window_s)[0], sm.window_s


@pytest.fixture(scope="session")
def other_account():
    """A second local account (uid), for attacks by another user of a shared host: created
    with useradd when the tests run as root (removed at the end), else the tests skip."""
    import pwd
    import shutil
    import subprocess

    if os.geteuid() != 0 or not shutil.which("useradd"):
        pytest.skip("needs root and useradd to create a second local account")
    name = f"tcspct{os.getpid() % 100000}"
    subprocess.run(["useradd", "--no-create-home", "--shell", "/usr/sbin/nologin", name],
                   check=True, capture_output=True)
    try:
        yield pwd.getpwnam(name).pw_uid
    finally:
        subprocess.run(["userdel", name], capture_output=True)


#: the modules `tcspc range`, `calibrate distance`, `histogram` and `decode` import,
#: imported once by :class:`CliProcess`'s server (~1.3 s a command's start-up)
_CLI_IMPORTS = ("numpy", "scipy.special", "scipy.stats", "scipy.optimize", "polars",
                "pyarrow.parquet", "pyarrow.compute", "pipeline.cli.app",
                "pipeline.cli.instruments", "pipeline.offline.generic",
                "pipeline.offline.ranging", "pipeline.offline.instruments",
                "pipeline.io.generic", "pipeline.io.ptu", "pipeline.io.linospad2")

#: the server: a request a line (argv, cwd, the stdout and stderr files, a timeout); the
#: child's exit status a line (null: killed at the timeout)
_CLI_SERVER = r"""
import atexit, importlib, json, os, select, signal, sys, traceback
for name in json.loads(sys.argv[1]):
    importlib.import_module(name)
from pipeline.cli.app import main
for line in sys.stdin:
    req = json.loads(line)
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            os.chdir(req["cwd"])
            os.dup2(os.open(os.devnull, os.O_RDONLY), 0)
            for fd, path in ((1, req["out"]), (2, req["err"])):
                os.dup2(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600), fd)
            sys.argv = ["tcspc", *req["argv"]]
            try:
                main()
                code = 0
            except SystemExit as e:
                if isinstance(e.code, str):
                    print(e.code, file=sys.stderr)
                code = e.code if isinstance(e.code, int) else (e.code is not None)
            atexit._run_exitfuncs()  # (what an exiting interpreter runs: PyTables' close)
        except BaseException:
            traceback.print_exc()
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(int(code))
    with os.fdopen(os.pidfd_open(pid)) as done:
        if not select.select([done], [], [], req["timeout"])[0]:
            os.kill(pid, signal.SIGKILL)
    status = os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])
    print(json.dumps(None if status == -signal.SIGKILL else status), flush=True)
"""


class CliProcess:
    """``python -m pipeline.cli ARGS`` as ``subprocess.run(..., capture_output=True,
    text=True)`` gives it (exit status, stdout, stderr), each command a process of its own
    forked from a server that imported the commands' modules once: a start-up is ~1.3 s
    of imports, ~30 of them in test_generic.py and test_cli_instruments.py. Started on
    first use."""

    def __init__(self, tmp: Path):
        self.tmp, self.proc, self.n = tmp, None, 0

    def run(self, *args, cwd=None, timeout: float = 300) -> subprocess.CompletedProcess:
        if self.proc is None or self.proc.poll() is not None:
            root = str(Path(__file__).parents[1])
            self.proc = subprocess.Popen(
                [sys.executable, "-c", _CLI_SERVER, json.dumps(_CLI_IMPORTS)],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                env={**os.environ, "PYTHONPATH": root}, cwd=root)
        self.n += 1
        out, err = self.tmp / f"{self.n}.out", self.tmp / f"{self.n}.err"
        argv = [str(a) for a in args]
        self.proc.stdin.write(json.dumps({"argv": argv, "cwd": str(cwd or os.getcwd()),
                                          "out": str(out), "err": str(err),
                                          "timeout": timeout}) + "\n")
        self.proc.stdin.flush()
        code = json.loads(self.proc.stdout.readline())
        if code is None:
            raise subprocess.TimeoutExpired(["tcspc", *argv], timeout)
        return subprocess.CompletedProcess(["tcspc", *argv], code, out.read_text(),
                                           err.read_text())

    def close(self) -> None:
        if self.proc is not None:
            self.proc.stdin.close()
            self.proc.wait(timeout=30)


@pytest.fixture(scope="session")
def cli_process(tmp_path_factory):
    """A :class:`CliProcess` of this test process."""
    p = CliProcess(tmp_path_factory.mktemp("cli"))
    yield p
    p.close()
