"""One fixture runs the stream's stages in both modes (bytewax's idea, STYLE.md): as
separate processes, as a user and the daemon start them, and as threads of the test's
own process. The commands, sockets and cores are the same; the two must never drift."""

import subprocess
import sys
import threading

import pytest


@pytest.fixture(params=["processes", "in-process"])
def run_stages(request):
    """``run_stages(args, args, ...)`` runs each ``tcspc stage ARGS`` to its end, all at once,
    as processes or as threads (``run_stages.mode``)."""

    def run(*commands, timeout=120):
        if request.param == "processes":
            procs = [subprocess.Popen([sys.executable, "-m", "pipeline.cli", "stage", *c])
                     for c in commands]
            for p in procs:
                assert p.wait(timeout=timeout) == 0
            return
        from pipeline.cli import cli

        errors = []

        def one(args):
            try:
                cli.main(args=["stage", *args], standalone_mode=False)
            except BaseException as exc:  # noqa: BLE001 - reported by the test
                errors.append(exc)

        threads = [threading.Thread(target=one, args=(c,), daemon=True) for c in commands]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout)
        assert not any(t.is_alive() for t in threads), "a stage did not finish"
        assert not errors, errors

    run.mode = request.param
    return run


@pytest.fixture(scope="session")
def daemon_helpers():
    """test_daemon.py's scene and helpers (``topology``, ``run_daemon``, ``dataset``, ``N``),
    loaded by path (tests/ is not a package)."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location(
        "_test_daemon_helpers", Path(__file__).with_name("test_daemon.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
