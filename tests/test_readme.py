"""README's "Useful commands" run as written: every command, option and input of the block
is checked here (fast), the cheap ones run, and the whole block runs in order through
examples/readme_commands.sh in the slow suite. The block starts by putting `tcspc` on the
PATH (``. .venv/bin/activate``); the tests give their directory a ``.venv`` (the one
running them). README stays a front door: under 100 lines."""

import os
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]


ACTIVATE = ". .venv/bin/activate"


def readme_lines() -> list[str]:
    """The lines of the sh block under "## Useful commands", comments dropped (what
    examples/readme_commands.sh pipes to sh)."""
    text = (ROOT / "README.md").read_text()
    block = re.search(r"^## Useful commands\n.*?^```sh\n(.*?)^```", text, re.S | re.M)
    assert block, 'README.md has no "## Useful commands" sh block'
    return [re.sub(r"  +# .*$", "", line) for line in block.group(1).splitlines()
            if line.strip()]


def readme_commands() -> list[str]:
    """The block's commands, after the line that activates .venv."""
    lines = readme_lines()
    assert lines[0] == ACTIVATE, f"the block starts with {ACTIVATE!r}, found {lines[0]!r}"
    return lines[1:]


def test_readme_is_a_front_door():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) < 100, f"README.md has {len(lines)} lines"


def expanded() -> list[list[str]]:
    """Each command as argv; a ``for x in ...; do CMD; done`` line gives one per value."""
    out = []
    for line in readme_commands():
        loop = re.fullmatch(r"for (\w+) in ([^;]+); do (.+); done", line)
        if loop:
            var, values, body = loop.groups()
            out += [shlex.split(body.replace(f"${var}", v)) for v in values.split()]
        else:
            out.append(shlex.split(line))
    return out


def _command(argv):
    import click

    from pipeline.cli.app import cli

    cmd, words = cli, argv[1:]
    ctx = click.Context(cli)
    while isinstance(cmd, click.Group) and words and not words[0].startswith("-"):
        sub = cmd.get_command(ctx, words[0])
        assert sub is not None, f"{shlex.join(argv)}: no command {words[0]!r}"
        cmd = sub._load() if hasattr(sub, "_load") else sub
        words = words[1:]
    return cmd, words


def test_every_command_option_and_input_is_known():
    made: set[str] = set()
    for argv in expanded():
        assert argv[0] == "tcspc", argv
        cmd, words = _command(argv)
        opts = {o for p in cmd.params for o in getattr(p, "opts", [])}
        flags = {o for p in cmd.params if getattr(p, "is_flag", False) for o in p.opts}
        i = 0
        while i < len(words):
            w = words[i]
            if w.startswith("-"):
                assert w in opts, f"{shlex.join(argv)}: {cmd.name} has no option {w}"
                if w == "--out":
                    made.add(words[i + 1])
                    i += 2
                    continue
                if w not in flags:
                    i += 1
                    w = words[i]
                else:
                    i += 1
                    continue
            if re.search(r"\.(toml|bin|ptu)$|^out/", w):
                known = (ROOT / w).exists() or w in made
                assert known, f"{shlex.join(argv)}: {w} is neither in the repository nor " \
                              "written by an earlier command"
            if w.endswith(".toml") and "daemon" in argv:
                topo = tomllib.loads((ROOT / w).read_text())
                assert (ROOT / topo["source"]["scene"]).exists()
                assert topo["range"]["calibration"] in made
            i += 1


def _env():
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}:{env.get('PATH', '')}"
    env["PYTHONPATH"] = f"{ROOT}:{env.get('PYTHONPATH', '')}"
    return env


def test_the_instrument_command_runs_as_written(tmp_path):
    """The cheapest command of the block, exactly as written, from a root-like directory."""
    for name in ("scenes", "examples", "tests"):
        (tmp_path / name).symlink_to(ROOT / name)
    (tmp_path / ".venv").symlink_to(Path(sys.executable).parents[1])
    (line,) = [c for c in readme_commands() if ".ptu" in c]
    proc = subprocess.run(f"{ACTIVATE} && {line}", shell=True, cwd=tmp_path, env=_env(),
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (tmp_path / "out" / "h.parquet").stat().st_size > 0


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_readme_commands_run_in_order(tmp_path):
    for name in ("scenes", "examples", "tests", "README.md"):
        (tmp_path / name).symlink_to(ROOT / name)
    (tmp_path / ".venv").symlink_to(Path(sys.executable).parents[1])
    proc = subprocess.run(["sh", "examples/readme_commands.sh"], cwd=tmp_path, env=_env(),
                          capture_output=True, text=True, timeout=3600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    import polars as pl

    # every pixel of the street's targets is detected; the unlit ones only at the stated
    # false-alarm rate (P_fa 1e-3 a pixel: 68 unlit pixels give 0.07 a run on average and
    # 3 or more with probability 5e-5; the chain's empty street gave 1 of 2 048 on 16 seeds)
    targets = tomllib.loads((ROOT / "scenes" / "street.toml").read_text())["targets"]
    lit = {p for t in targets for p in range(t["pixels"][0], t["pixels"][1] + 1)}
    ranges = pl.read_parquet(tmp_path / "out" / "ranges.parquet")
    found = set(ranges.filter(pl.col("detected"))["tdc"].to_list())
    assert lit <= found, sorted(lit - found)
    assert len(found - lit) <= 2, sorted(found - lit)
    assert list((tmp_path / "out" / "stream" / "ranges").rglob("*.parquet"))
