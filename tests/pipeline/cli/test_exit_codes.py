"""The exit-code contract (docs/design.md "Exit codes"): every command through its error
paths, each status and its one-line message held.

The table in docs/design.md is read here. A command of `tcspc` without rows there fails
(:func:`test_every_command_has_rows`); a row for status 2 or 3 without a case below fails
(:func:`test_every_refusal_row_is_driven`); a case whose command ends with another status,
a traceback, more than one line of error or click's usage block fails
(:func:`test_each_case_ends_as_the_table_says`).

Adding a command (or a status to one): add its rows to the table in docs/design.md
(``| `tcspc NAME SUB` | STATUS | when |``, one row per status) and, for each row with
status 2 or 3, one or more entries to CASES below: ``("tcspc NAME SUB", STATUS, argv,
fragment)`` with argv a function of the fixture ``f`` (paths of small files made once:
see :func:`f`) and ``fragment`` a piece of the expected stderr. A status driven by a
slower test elsewhere goes in ELSEWHERE instead, naming that test (checked to exist).
"""

from __future__ import annotations

import re
import socket
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

ROOT = Path(__file__).parents[3]
DATA = ROOT / "tests" / "data"
T3 = DATA / "picoquant" / "hydraharp_v20_t3.ptu"


def table_rows() -> dict[str, dict[int, str]]:
    """{command: {status: when}} from docs/design.md's "Exit codes" table."""
    text = (ROOT / "docs" / "design.md").read_text()
    section = re.search(r"^## Exit codes\n(.*?)^## ", text, re.S | re.M)
    assert section, 'docs/design.md has no "## Exit codes" section'
    rows: dict[str, dict[int, str]] = {}
    for cmd, code, when in re.findall(r"^\| `(tcspc[^`]*)` \| (\d+) \| (.+?) \|$",
                                      section.group(1), re.M):
        rows.setdefault(cmd, {})[int(code)] = when
    return rows


def cli_commands() -> list[str]:
    """Every command of `tcspc` that runs (groups' leaves), as "tcspc a b"."""
    import click

    from pipeline.cli.app import cli
    from pipeline.cli.docs import _walk

    root = click.Context(cli, info_name="tcspc")
    return [" ".join(path) for path, cmd, _ in _walk(cli, root, ["tcspc"])
            if not isinstance(cmd, click.Group)]


# (command, status, argv from the fixture f, a fragment of stderr)
CASES = [
    # decode and histogram: what the input is, the options, the output, a cut-short input
    ("tcspc decode", 2, lambda f: ["decode", f.missing, "--out", f.new("e.parquet")],
     "no such file"),
    ("tcspc decode", 2, lambda f: ["decode", f.dir, "--out", f.new("e.parquet")],
     "a directory"),
    ("tcspc decode", 2, lambda f: ["decode", f.png, "--out", f.new("e.parquet")],
     "give --format tcspc|ptu|linospad2"),
    ("tcspc decode", 2, lambda f: ["decode", f.cap, "--out", f.new("e.parquet"),
                                   "--engine", "cuda"], "--engine"),
    ("tcspc decode", 2, lambda f: ["decode", T3, "--out", f.new("e.parquet"),
                                   "--include-no-hit"], "not for a ptu file"),
    ("tcspc decode", 2, lambda f: ["decode", f.cap, "--out", f.ranges], "not replaced"),
    ("tcspc decode", 3, lambda f: ["decode", f.cut, "--out", f.new("e.parquet"), "-q"],
     "cut short"),
    ("tcspc decode", 3, lambda f: ["decode", f.cut_ptu, "--out", f.new("e.parquet"), "-q"],
     "truncated"),
    ("tcspc histogram", 2, lambda f: ["histogram", f.empty_parquet, "--out",
                                      f.new("h.parquet")], "an empty file (0 bytes)"),
    ("tcspc histogram", 2, lambda f: ["histogram", f.ranges, "--out", f.new("h.parquet")],
     "a parquet file; this command takes"),
    ("tcspc histogram", 2, lambda f: ["histogram", f.cap, "--out", f.ranges, "--overwrite"],
     "holds a ranges table, not histograms: not replaced"),
    ("tcspc histogram", 2, lambda f: ["histogram", f.cap, "--out", f.png_out],
     "is not a parquet file"),
    ("tcspc histogram", 2, lambda f: ["histogram", f.cap, "--out", f.under_file],
     "is a file, not a directory"),
    ("tcspc histogram", 2, lambda f: ["histogram", f.cap, "--out", f.dir], "a directory"),
    ("tcspc histogram", 2, lambda f: ["histogram", f.cap, "--bogus"], "No such option"),
    ("tcspc histogram", 3, lambda f: ["histogram", f.cut, "--out", f.new("h.parquet")],
     "--allow-truncated"),
    ("tcspc pattern", 2, lambda f: ["pattern", f.new("p"), "--cycles", "0"], "--cycles"),
    ("tcspc pattern", 2, lambda f: ["pattern", f.new("p"), "--cycles", "10" * 8],
     "free on"),
    ("tcspc pattern", 2, lambda f: ["pattern", f.cap], "exists; give --overwrite"),
    ("tcspc schema", 2, lambda f: ["schema", "--bogus"], "No such option"),
    # calibrate plan: the zero capture, the budget, the output
    ("tcspc calibrate plan", 2, lambda f: ["calibrate", "plan", f.missing, "--cycles-budget",
                                           "1e6", "--out", f.new("p.json")], "capture not found"),
    ("tcspc calibrate plan", 2, lambda f: ["calibrate", "plan", f.cap, "--cycles-budget",
                                           "10", "--out", f.new("p.json")], "--cycles-budget"),
    ("tcspc calibrate plan", 2, lambda f: ["calibrate", "plan", f.cap, "--cycles-budget",
                                           "1e6", "--out", f.ranges], "exists; give --overwrite"),
    # export: the geometry, the format, the output (tests/pipeline/io/test_pointcloud.py)
    ("tcspc export", 2, lambda f: ["export", f.ranges, "--geometry", "nowhere.toml",
                                   "--out", f.new("p.las")], "nowhere.toml"),
    ("tcspc export", 2, lambda f: ["export", f.ranges, "--geometry", "thesis128",
                                   "--out", f.new("p.xyz")], "--format"),
    ("tcspc export", 2, lambda f: ["export", f.ranges, "--geometry", "thesis128",
                                   "--format", "las", "--out", f.ranges],
     "exists; give --overwrite"),
    ("tcspc simulate", 2, lambda f: ["simulate", f.scene, "--cycles", "1000000000000000",
                                     "--out", f.new("s.bin")], "needs ~"),
    ("tcspc simulate", 2, lambda f: ["simulate", f.scene, "--out", f.cap],
     "exists; give --overwrite"),
    ("tcspc simulate", 2, lambda f: ["simulate", f.bad_scene, "--out", f.new("s.bin")],
     "bad.toml"),
    ("tcspc simulate", 2, lambda f: ["simulate", f.scene, "--out", f.under_file],
     "cannot be written"),
    ("tcspc range", 2, lambda f: ["range", f.cap, "--out", f.new("r.parquet")],
     "needs --calibration"),
    ("tcspc range", 2, lambda f: ["range", T3, "--out", f.new("r.parquet"),
                                  "--calibration", f.dir], "--calibration is the thesis"),
    ("tcspc range", 2, lambda f: ["range", f.generic, "--out", f.new("r.parquet"),
                                  "--calibration", f.chip_cal], "calibrate distance"),
    ("tcspc range", 2, lambda f: ["range", T3, "--out", f.new("r.parquet"),
                                  "--delay-ps", "1", "--gate", "5"], "LO:HI"),
    ("tcspc range", 2, lambda f: ["range", T3, "--out", f.new("r.parquet"),
                                  "--p-fa", "2"], "p_fa"),
    ("tcspc range", 2, lambda f: ["range", f.cap, "--out", f.hist_out,
                                  "--calibration", f.dir], "not replaced"),
    # the estimators' checks at the door (docs/ranging.md; the hard cases of
    # test_cli_range_hard.py, each held here at its status)
    ("tcspc range", 2, lambda f: ["range", f.hand(0.0), "--out", f.new("r.parquet"),
                                  "--delay-ps", "1000"], "bin widths"),
    ("tcspc range", 2, lambda f: ["range", f.hand(16.0, bins=0), "--out", f.new("r.parquet"),
                                  "--delay-ps", "1000"], "at least one bin"),
    ("tcspc range", 2, lambda f: ["range", f.hand(16.0), "--out", f.new("r.parquet"),
                                  "--delay-ps", "1000", "--irf-ps", "1e9"], "no wider"),
    ("tcspc range", 2, lambda f: ["range", f.hand(16.0), "--out", f.new("r.parquet"),
                                  "--delay-ps", "nan"], "--delay-ps must be finite"),
    ("tcspc range", 2, lambda f: ["range", f.other_chip()[0], "--out", f.new("r.parquet"),
                                  "--calibration", f.other_chip()[1]],
     "does not match calibration"),
    ("tcspc range", 2, lambda f: ["range", T3, "--out", f.new("r.parquet"), "--delay-ps", "0",
                                  "--force"], "--force is for a tcspc capture"),
    ("tcspc range", 3, lambda f: ["range", f.cut_ptu, "--out", f.new("r.parquet"),
                                  "--delay-ps", "1000"], "nothing written"),
    ("tcspc calibrate delay", 2, lambda f: ["calibrate", "delay", f.cap, "--out", f.dir],
     "not a calibration directory"),
    ("tcspc calibrate density", 2, lambda f: ["calibrate", "density", f.missing,
                                              "--out", f.new("c")], "not found"),
    ("tcspc calibrate density", 2, lambda f: ["calibrate", "density", f.cap,
                                              "--out", f.under_file], "cannot be written"),
    ("tcspc calibrate density", 2, lambda f: ["calibrate", "density", f.cap,
                                              "--out", f.other_dir], "holds other files"),
    ("tcspc calibrate distance", 2, lambda f: ["calibrate", "distance", f.generic,
                                               "--truth", f.empty_csv,
                                               "--out", f.new("dc")], "needs the columns"),
    ("tcspc calibrate distance", 2, lambda f: ["calibrate", "distance", f.generic,
                                               "--truth", f.truth, "--out", f.png_out],
     "takes a directory"),
    ("tcspc calibrate lsb", 2, lambda f: ["calibrate", "lsb", f.cap, "--out", f.new("l")],
     "light levels"),
    ("tcspc calibrate lsb", 2, lambda f: ["calibrate", "lsb", f.cap, "--out", f.chip_cal],
     "exists; give --overwrite"),
    ("tcspc calibrate track", 2, lambda f: ["calibrate", "track", f.cap, "--calibration",
                                            f.missing], "does not exist"),
    ("tcspc daemon", 2, lambda f: ["daemon", "--config", f.bad_topology], "bad_topology"),
    ("tcspc status", 2, lambda f: ["status", "--state", f.dir], "no status"),
    ("tcspc view", 2, lambda f: ["view", "--port", f.busy_port, "--nice", "0", "--state",
                                 f.dir, "--out", f.dir], "cannot listen"),
    ("tcspc view", 2, lambda f: ["view", "--layout", "7x", "--nice", "0"], "--layout"),
    ("tcspc journal export", 2, lambda f: ["journal", "export", f.missing, f.new("j")],
     "does not exist"),
    ("tcspc journal export", 2, lambda f: ["journal", "export", f.cap, f.cap],
     "exists; give --overwrite"),
    ("tcspc stage histogram", 2, lambda f: ["stage", "histogram", "--bogus"],
     "No such option"),
    ("tcspc stage ingest-udp", 2, lambda f: ["stage", "ingest-udp", "--bogus"],
     "No such option"),
    ("tcspc stage plan", 2, lambda f: ["stage", "plan", "--config", f.bad_topology,
                                       "--out", f.new("plan")], "bad_topology"),
    ("tcspc stage range", 2, lambda f: ["stage", "range", "--bogus"], "No such option"),
    ("tcspc stage sink", 2, lambda f: ["stage", "sink", "--bogus"], "No such option"),
    ("tcspc stage source-capture", 2, lambda f: ["stage", "source-capture", f.missing,
                                                 "--push", "ipc:///nowhere"], "not found"),
    ("tcspc stage source-file", 2, lambda f: ["stage", "source-file", f.missing,
                                              "--push", "ipc:///nowhere"], "does not exist"),
    ("tcspc stage source-sim", 2, lambda f: ["stage", "source-sim", f.missing,
                                             "--push", "ipc:///nowhere"], "does not exist"),
    ("tcspc model ambient", 2, lambda f: ["model", "ambient", "--lux", "bright"], "--lux"),
    ("tcspc model figures", 2, lambda f: ["model", "figures", "--out", f.under_file],
     "cannot be written"),
    ("tcspc model histogram", 2, lambda f: ["model", "histogram", f.missing],
     "does not exist"),
    ("tcspc model link-budget", 2, lambda f: ["model", "link-budget", "-d", "far"],
     "--distance"),
    ("tcspc model predict", 2, lambda f: ["model", "predict", "-c", "9"], "--config"),
    ("tcspc model predict", 2, lambda f: ["model", "predict", "-c", "1", "--out",
                                          f.ranges], "exists; give --overwrite"),
    ("tcspc model table", 2, lambda f: ["model", "table", "--bogus"], "No such option"),
    ("tcspc model transmission", 2, lambda f: ["model", "transmission", "-d", "far"],
     "--distance"),
    ("tcspc flow list", 2, lambda f: ["flow", "list", "--bogus"], "No such option"),
    ("tcspc flow run", 2, lambda f: ["flow", "run", "no-such-flow"], "no-such-flow"),
    ("tcspc flow automations", 2, lambda f: ["flow", "automations", "--stale-hours", "0"],
     "--stale-hours"),
    ("tcspc flow serve", 2, lambda f: ["flow", "serve", "--calibration-cron", "every day"],
     "every day"),
    ("tcspc demo", 2, lambda f: ["demo", "--cycles", "0"], "--cycles"),
    ("tcspc demo", 3, lambda f: ["demo", "--out", f.new("demo")], "a check failed"),
]

#: statuses held by a test elsewhere (slower: a whole daemon run or flow): the test named
ELSEWHERE = {
    ("tcspc daemon", 1): "tests/pipeline/stream/test_lifecycle.py::"
                         "test_a_run_that_does_not_balance_is_never_finished",
    ("tcspc daemon", 3): "tests/pipeline/stream/test_lifecycle.py::"
                         "test_a_run_that_does_not_balance_is_never_finished",
    ("tcspc daemon", 130): "tests/pipeline/stream/test_lifecycle.py::"
                           "test_ctrl_c_then_a_restart_gives_the_uninterrupted_runs_datasets",
    ("tcspc reconcile", 2): "tests/pipeline/stream/test_resume.py::"
                            "test_reconcile_finishes_a_run_offline_and_again_changes_nothing",
    ("tcspc reconcile", 3): "tests/pipeline/stream/test_resume.py::"
                            "test_reconcile_finishes_a_run_offline_and_again_changes_nothing",
    ("tcspc flow run", 3): "tests/flows/test_flows.py::"
                           "test_a_current_that_cannot_be_read_is_not_replaced_unexamined",
}


@pytest.fixture(scope="module")
def f(tmp_path_factory):
    """Small files of every kind the cases need, made once."""
    from pipeline.io.capture import CaptureWriter
    from pipeline.io.tmf8820 import tmf8820_table
    from stages.testpattern import pattern_words

    d = tmp_path_factory.mktemp("exit")
    words, _ = pattern_words(400, 8, hit_prob=0.2, rng=1)
    with CaptureWriter(d / "cap.bin", 8, kind="pattern") as w:
        w.write(words)
    (d / "cut.json").write_text((d / "cap.json").read_text())
    (d / "cut.bin").write_bytes((d / "cap.bin").read_bytes()[:4 * 8 * 150 + 6])
    (d / "cut.ptu").write_bytes(T3.read_bytes()[:-1000])
    (d / "pic.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    (d / "out.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    (d / "empty.parquet").write_bytes(b"")
    (d / "adir").mkdir()
    (d / "other").mkdir()
    (d / "other" / "notes.txt").write_text("mine")
    (d / "chipcal").mkdir()
    (d / "chipcal" / "tdc.parquet").write_bytes(b"PAR1")
    (d / "afile").write_text("x")
    pq.write_table(pa.table({"tdc": [0]}).replace_schema_metadata({b"tcspc.schema": b"ranges"}),
                   d / "ranges.parquet")
    pq.write_table(pa.table({"tdc": [0]}).replace_schema_metadata(
        {b"tcspc.schema": b"histograms"}), d / "hist.parquet")
    import json

    caps = json.loads((DATA / "tmf8820" / "distance_data_even.json").read_text())[:3]
    table, truth = tmf8820_table(caps)
    pq.write_table(table, d / "generic.parquet")
    (d / "truth.csv").write_text("measurement,distance_m\n"
                                 + "".join(f"{m},{x}\n" for m, x in truth))
    (d / "empty.csv").write_text("")
    (d / "scene.toml").write_text((ROOT / "examples" / "zero.toml").read_text())
    (d / "bad.toml").write_text("[sensor]\nn_pixels = -3\nbogus = 1\n")
    (d / "bad_topology.toml").write_text("[daemon]\nbogus = 1\n")
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    made = iter(range(10**6))

    def hand(width_ps: float, bins: int = 2000) -> Path:
        """A histograms 2.0 file as another tool would write it (one return)."""
        from schemas.outputs import HISTOGRAMS

        counts = np.random.default_rng(0).poisson(1.0, bins)
        counts[bins // 2 - 2:bins // 2 + 2] += 400 if bins else 0
        path = d / f"hand-{width_ps}-{bins}.parquet"
        zero = {k: pa.array([0], pa.uint64()) for k in ("n_no_hit", "n_artifact",
                                                        "n_invalid_phase", "n_malformed")}
        pq.write_table(pa.table({
            "measurement": ["hand"], "tdc": pa.array([0], pa.uint16()),
            "cycles": pa.array([10**6], pa.uint64()),
            "counts": pa.array([counts.tolist()], pa.list_(pa.uint64())),
            "n_hit": pa.array([int(counts.sum())], pa.uint64()), **zero,
            "instrument": ["picoquant-t3"], "bin_width_ps": pa.array([width_ps])},
            schema=HISTOGRAMS.schema), path)
        return path

    made_pair: list = []

    def other_chip() -> tuple[Path, Path]:
        """A capture of one zoo chip and a calibration of another (made on first use)."""
        if not made_pair:
            from benchmarks.calibration_sigma import (
                chip_of,
                save_chip_calibration,
                simulated_capture,
            )

            made_pair.extend([simulated_capture(chip_of(2, 8), d / "chip2.bin"),
                              save_chip_calibration(chip_of(1, 8), 1, d / "chip1cal")])
        return made_pair[0], made_pair[1]

    ns = SimpleNamespace(
        cap=d / "cap.bin", cut=d / "cut.bin", cut_ptu=d / "cut.ptu", png=d / "pic.png",
        png_out=d / "out.png", empty_parquet=d / "empty.parquet", dir=d / "adir",
        other_dir=d / "other", chip_cal=d / "chipcal", ranges=d / "ranges.parquet",
        hist_out=d / "hist.parquet", generic=d / "generic.parquet", truth=d / "truth.csv",
        empty_csv=d / "empty.csv", scene=d / "scene.toml", bad_scene=d / "bad.toml",
        bad_topology=d / "bad_topology.toml", missing=d / "missing.bin",
        under_file=d / "afile" / "x.parquet", busy_port=busy.getsockname()[1],
        new=lambda name: d / f"new{next(made)}" / name, hand=hand, other_chip=other_chip)
    yield ns
    busy.close()


def run(argv, capsys) -> tuple[int, str]:
    """The command in this process, as the `tcspc` script runs it: (status, stderr)."""
    from pipeline.cli.app import cli

    capsys.readouterr()
    with pytest.raises(SystemExit) as ended:
        cli.main([str(a) for a in argv], prog_name="tcspc")
    return ended.value.code, capsys.readouterr().err


def test_every_command_has_rows():
    rows = table_rows()
    missing = [c for c in cli_commands() if c not in rows]
    assert not missing, f"commands without rows in docs/design.md's exit codes: {missing}"
    stale = [c for c in rows if c not in cli_commands()]
    assert not stale, f"rows for commands that do not exist: {stale}"
    for cmd, codes in rows.items():
        assert 0 in codes and 2 in codes, f"{cmd}: a row for 0 and for 2, at least"
        assert set(codes) <= {0, 1, 2, 3, 130}, f"{cmd}: {sorted(codes)}"


def test_every_refusal_row_is_driven():
    driven = {(c, s) for c, s, _, _ in CASES} | set(ELSEWHERE)
    rows = table_rows()
    undriven = [(c, s) for c, codes in rows.items() for s in codes
                if s in (2, 3) and (c, s) not in driven]
    assert not undriven, f"rows no case drives: {undriven}"
    assert {(c, s) for c, s, _, _ in CASES} <= {(c, s) for c, codes in rows.items()
                                                for s in codes}, "a case without its row"
    for (cmd, status), where in ELSEWHERE.items():
        assert status in rows[cmd], (cmd, status)
        path, name = where.split("::")
        assert f"def {name}(" in (ROOT / path).read_text(), where


@pytest.mark.parametrize("cmd, status, argv, fragment", CASES,
                         ids=[f"{c[6:]}-{s}-{i}" for i, (c, s, _, _) in enumerate(CASES)])
def test_each_case_ends_as_the_table_says(cmd, status, argv, fragment, f, capsys,
                                          monkeypatch):
    if cmd == "tcspc demo" and status == 3:  # a check that fails, without the whole story
        import flows.demo

        monkeypatch.setattr(flows.demo, "run_story", lambda out, cycles: {"ok": False})
    code, err = run(argv(f), capsys)
    assert code == status, f"{cmd}: exit {code}, the table says {status}: {err}"
    assert "Traceback" not in err and "Usage:" not in err, err
    # one line per problem (a config's problems are all listed, one a line)
    errors = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert errors, err
    assert any(fragment in e for e in errors), f"{fragment!r} not in {errors!r}"
    assert ".tmp-" not in err  # (the user's path, never an internal temporary)


def test_a_group_named_alone_shows_its_help(capsys):
    code, err = run(["calibrate"], capsys)
    assert code == 2 and "Commands:" in err and "error:" not in err


def test_an_internal_error_is_one_line_and_exit_1(capsys, monkeypatch):
    """A bug (here a function that raises what no check expects) is exit 1, one line."""
    import pipeline.cli.app as app

    def broken(*a, **k):
        raise ZeroDivisionError("boom")

    monkeypatch.setattr(app, "_range", broken)
    code, err = run(["range", "x", "--out", "/tmp/none/x.parquet", "--overwrite"], capsys)
    assert code == 1 and "internal error" in err and "boom" in err
    assert len(err.strip().splitlines()) == 1, err


def test_nothing_is_written_where_an_output_is_refused(f, capsys):
    before = f.ranges.read_bytes()
    code, _ = run(["histogram", f.cap, "--out", f.ranges, "--overwrite"], capsys)
    assert code == 2 and f.ranges.read_bytes() == before
    out = f.new("twice.parquet")
    assert run(["histogram", f.cap, "--out", out, "-q"], capsys)[0] == 0
    first = out.read_bytes()
    code, err = run(["histogram", f.cap, "--out", out, "-q"], capsys)
    assert code == 2 and "exists; give --overwrite" in err and out.read_bytes() == first
    assert run(["histogram", f.cap, "--out", out, "-q", "--overwrite"], capsys)[0] == 0
    assert not list(out.parent.glob(".*tmp*"))


def test_a_cut_short_capture_is_written_whole_cycles_flagged(f, capsys):
    out = f.new("cut.parquet")
    code, err = run(["histogram", f.cut, "--out", out, "-q"], capsys)
    assert code == 3
    assert pq.read_schema(out).metadata[b"tcspc.truncated"] == b"True"
    import polars as pl

    assert pl.read_parquet(out)["cycles"].to_list() == [150] * 8
    code, err = run(["histogram", f.cut, "--out", out, "-q", "--allow-truncated",
                     "--overwrite"], capsys)
    assert code == 0 and "cut short" in err
    assert np.all(pl.read_parquet(out)["cycles"].to_numpy() == 150)
