"""The daemon at the door (issues 26.5, 26.6, 26.9, 27.4, 27.5): a topology checked whole at
load, resources probed and the state directory taken before any stage starts."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.stream.state import StateError, check_resources, open_state
from pipeline.stream.topology import TopologyError, load_topology
from pipeline.stream.wire import ID_PATTERN, run_id_from

SCENE = (Path(__file__).parents[3] / "scenes" / "small16.toml").read_text()


def write_topology(tmp_path, source=None, histogram="workers = 1\nmeasurement_cycles = 10000",
                   extra="", state=None, name="small"):
    (tmp_path / f"{name}.toml").write_text(SCENE)
    source = source or f'kind = "sim"\nscene = "{tmp_path / (name + ".toml")}"\ncycles = 1000'
    text = (f'[daemon]\nstate = "{state or tmp_path / "state"}"\n[source]\n{source}\n'
            f'[histogram]\n{histogram}\n{COUNT}\n[sink]\nout = "{tmp_path / "out"}"\n{extra}')
    path = tmp_path / "topo.toml"
    path.write_text(text)
    return path


# sim and udp sources without a calibration ask for their artifacts to be counted
COUNT = 'artifacts = "count-as-hits"'
UDP = 'kind = "udp"\nbind = "127.0.0.1:9000"\nn_tdc = 16'

# (section, key, the [source] lines or a section's lines, where they go)
CASES = [
    ("source", "bind", 'kind = "udp"\nbind = "127.0.0.1:70000"\nn_tdc = 16', None),
    ("view", "port", None, "[view]\nport = 70000\n"),
    ("histogram", "measurement_cycles", None, "measurement_cycles = -5"),
    ("histogram", "measurement_cycles", None, "measurement_cycles = 0"),
    ("histogram", "measurement_cycles", None, 'measurement_cycles = "20000"'),
    ("source", "reorder_window", UDP + "\nreorder_window = 0", None),
    ("source", "max_jump_cycles", UDP + "\nmax_jump_cycles = -1", None),
    ("source", "n_tdc", 'kind = "udp"\nbind = "127.0.0.1:9000"\nn_tdc = 300', None),
    ("source", "idle", UDP + "\nidle = -1", None),
    ("histogram", "workers", None, 'workers = "two"'),
    ("sink", "out", None, None),  # out under /proc (below)
    ("daemon", "hwm", None, "hwm = 0"),
    ("histogram", "colour", None, "colour = 1"),
    ("source", "cycles", UDP + "\ncycles = 5", None),
]


@pytest.mark.parametrize("sec,key,source,lines", CASES,
                         ids=[f"{s}.{k}-{i}" for i, (s, k, *_) in enumerate(CASES)])
def test_each_bad_value_is_named_with_its_file_section_and_key(tmp_path, sec, key, source,
                                                               lines):
    hist = "workers = 1"
    extra = ""
    if sec == "histogram":
        hist = lines
    elif lines and lines.startswith("[view]"):
        extra = lines
    elif sec == "daemon":
        extra = ""
    path = write_topology(tmp_path, source, hist, extra)
    if sec == "daemon":
        path.write_text(path.read_text().replace("[source]", f"{lines}\n[source]", 1))
    if sec == "sink":
        path.write_text(path.read_text().replace(f'out = "{tmp_path / "out"}"',
                                                 'out = "/proc/tcspc/out"'))
    with pytest.raises(TopologyError) as exc:
        load_topology(path)
    lines_out = str(exc.value).splitlines()
    assert len(lines_out) == 1, lines_out  # one problem, one line
    assert lines_out[0].startswith(f"{path} [{sec}] {key}"), lines_out[0]


def test_every_problem_in_one_pass_exit_2_and_nothing_started(tmp_path):
    path = write_topology(tmp_path, UDP.replace("9000", "70000") + "\nidle = -1\ncycles = 3",
                          'workers = "two"\nmeasurement_cycles = 0',
                          "[view]\nport = 70000\n")
    with pytest.raises(TopologyError) as exc:
        load_topology(path)
    keys = [line.split("] ", 1)[1].split(" ")[0].rstrip(":")
            for line in str(exc.value).splitlines()]
    assert sorted(keys) == sorted(["idle", "workers", "measurement_cycles", "port", "cycles",
                                   "bind"])
    r = subprocess.run([sys.executable, "-m", "pipeline.cli", "daemon", "--config", path],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "workers = 'two'" in r.stderr and "idle = -1" in r.stderr
    assert not (tmp_path / "state").exists() and not (tmp_path / "out").exists()


def test_run_ids_from_file_names_are_ones_the_daemon_takes(tmp_path):
    assert run_id_from("my street") == "my_street"
    assert ID_PATTERN.fullmatch(run_id_from("..")) and ID_PATTERN.fullmatch(run_id_from("é" * 9))
    assert len(run_id_from("x" * 200, "-20261127T000000Z")) == 64
    topo = load_topology(write_topology(tmp_path, name="my street"))
    assert topo.run.startswith("my_street-") and ID_PATTERN.fullmatch(topo.run)
    with pytest.raises(TopologyError, match="e.g. 'my_street'"):
        load_topology(write_topology(tmp_path), "my street")


# ---------------------------------------------------------------- the state directory
def test_the_state_is_created_private_whatever_the_umask(tmp_path):
    old = os.umask(0)
    try:
        lock = open_state(tmp_path / "a" / "state")
    finally:
        os.umask(old)
    assert (tmp_path / "a" / "state").stat().st_mode & 0o777 == 0o700
    lock.release()


@pytest.mark.parametrize("how", ["world-writable", "another user", "a file"])
def test_a_state_not_ours_is_refused(tmp_path, how):
    st = tmp_path / "state"
    if how == "a file":
        st.write_text("")
    else:
        st.mkdir()
        os.chmod(st, 0o777)
        if how == "another user":
            if os.geteuid() != 0:
                pytest.skip("making a directory of another user needs root")
            os.chmod(st, 0o700)
            os.chown(st, 4242, 4242)
    with pytest.raises(StateError, match=str(st)):
        open_state(st)


@pytest.mark.parametrize("name", ["view.url", "logs", "journal", "tokens", "quarantine"])
def test_links_planted_in_the_state_are_refused(tmp_path, name):
    st = tmp_path / "state"
    st.mkdir(mode=0o700)
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "precious").write_text("keep me")
    os.chmod(victim / "precious", 0o644)
    (st / name).symlink_to(victim / "precious" if name == "view.url" else victim)
    with pytest.raises(StateError, match=f"{st / name}: a symbolic link"):
        open_state(st)
    assert (victim / "precious").read_text() == "keep me"  # neither truncated nor written
    assert (victim / "precious").stat().st_mode & 0o777 == 0o644  # nor chmod'ed
    assert sorted(p.name for p in victim.iterdir()) == ["precious"]


def test_a_second_daemon_on_the_same_state_is_refused_with_the_first_ones_pid(tmp_path):
    st = tmp_path / "state"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from pipeline.stream.state import "
         f"open_state; lock = open_state({str(st)!r}); print('held', flush=True); "
         "time.sleep(60)"], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(StateError, match=f"in use by daemon pid {holder.pid}"):
            open_state(st)
    finally:
        holder.kill()
        holder.wait()
    open_state(st).release()  # the lock died with its process


# ---------------------------------------------------------------- resources
def test_a_busy_udp_port_fails_at_start_with_the_reason(tmp_path):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as busy:
        busy.bind(("127.0.0.1", 0))
        port = busy.getsockname()[1]
        path = write_topology(tmp_path, f'kind = "udp"\nbind = "127.0.0.1:{port}"\n'
                              'n_tdc = 16\nidle = 1')
        t0 = time.monotonic()
        r = subprocess.run([sys.executable, "-m", "pipeline.cli", "daemon", "--config", path],
                           capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert f"127.0.0.1:{port}" in r.stderr and "in use" in r.stderr
    assert time.monotonic() - t0 < 30  # not after a restart loop
    assert not list((tmp_path / "state" / "logs").glob("*.log"))  # no stage started


def test_a_busy_view_port_an_unwritable_out_and_a_long_state_fail_at_start(tmp_path):
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        topo = load_topology(write_topology(tmp_path, extra=f"[view]\nport = {port}\n"))
        with pytest.raises(StateError, match=rf"view: cannot listen on 127.0.0.1:{port}"):
            check_resources(topo)
    if (tmp_path / "out").is_dir():
        (tmp_path / "out").rmdir()  # (made by the probe above)
    topo = load_topology(write_topology(tmp_path))
    (tmp_path / "out").write_text("a file where the datasets go")  # (after the load)
    with pytest.raises(StateError, match=r"sink: cannot write the datasets"):
        check_resources(topo)
    (tmp_path / "out").unlink()
    deep = tmp_path / ("d" * 60) / ("e" * 60) / "state"
    topo = load_topology(write_topology(tmp_path, state=deep))
    with pytest.raises(StateError, match=r"the ipc path is \d+ bytes, the kernel takes 107"):
        check_resources(topo)


@pytest.mark.slow  # ~19 s on the loaded 2-core machine (the fast twin: the lock's pid above)
def test_a_second_daemon_is_refused_and_leaves_the_first_ones_run_alone(tmp_path):
    """Two `tcspc daemon` on one state: the second exits 2 naming the first's pid, starts no
    stage and does not touch its status.json."""
    path = write_topology(tmp_path, f'kind = "sim"\nscene = "{tmp_path / "small.toml"}"\n'
                          'cycles = 2000000\nrate = 2e6')
    first = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "daemon", "--config",
                              path, "--run", "one"], stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL)
    try:
        status = tmp_path / "state" / "status.json"
        deadline = time.time() + 60
        while not status.exists():
            assert first.poll() is None and time.time() < deadline
            time.sleep(0.1)
        r = subprocess.run([sys.executable, "-m", "pipeline.cli", "daemon", "--config", path,
                            "--run", "two"], capture_output=True, text=True, timeout=120)
        assert r.returncode == 2 and f"in use by daemon pid {first.pid}" in r.stderr
        assert '"run": "one"' in status.read_text()
        assert not list((tmp_path / "state" / "checkpoints").glob("two"))
    finally:
        first.kill()  # (its stages die with it)
        first.wait(timeout=60)
