"""The command line's printer: user text is printed as given, and no import circle."""

import ast
import io
import re
import subprocess
import sys
from pathlib import Path

from pipeline.cli.console import console, error, warn

CLI = Path(__file__).parents[3] / "pipeline" / "cli"


def _buffered():
    con = console(stderr=True)
    con.file = io.StringIO()
    return con


def test_bracketed_names_survive():
    con = _buffered()
    error("typo.toml [histogram]: unknown keys ['bins']", con)
    warn("journal words [0, 4096) skipped: [red]x[/red]", con)
    con.print("daemon: stage [sink] restarted")
    assert con.file.getvalue().splitlines() == [
        "error: typo.toml [histogram]: unknown keys ['bins']",
        "warning: journal words [0, 4096) skipped: [red]x[/red]",
        "daemon: stage [sink] restarted"]


def _imports(path: Path) -> set[str]:
    """pipeline.cli modules imported anywhere in ``path`` (module level or in a function)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module == "pipeline.cli":
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("pipeline.cli."):
            names.add(node.module.split(".")[2])
        elif isinstance(node, ast.Import):
            names |= {a.name.split(".")[2] for a in node.names
                      if a.name.startswith("pipeline.cli.")}
    return names


def test_no_import_circle_in_the_cli():
    graph = {p.stem: _imports(p) - {p.stem} for p in CLI.glob("*.py")}
    graph.pop("__init__", None)  # the package re-exports app; app does not import it
    graph.pop("__main__", None)

    def reach(start):
        seen, todo = set(), [start]
        while todo:
            for nxt in graph.get(todo.pop(), ()):
                if nxt not in seen:
                    seen.add(nxt)
                    todo.append(nxt)
        return seen

    circles = sorted(m for m in graph if m in reach(m))
    assert not circles, f"modules of pipeline/cli in an import circle: {circles}"


def _refused(cwd, *args) -> list[str]:
    """The stderr lines of ``tcspc ARGS`` run in ``cwd``, which must exit 2."""
    proc = subprocess.run([sys.executable, "-m", "pipeline.cli", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    return proc.stderr.splitlines()


TYPO = """name = "typo"
[gate]
t_laser_win_ns = "abc"
[histogram]
bins = 3
[[targets]]
pixels = [0, 300]
distance_m = 5.0
colour = "red"
"""


def test_a_bad_scene_is_every_problem_and_exit_2(tmp_path):
    """The CLI prints each problem on its own line with the section's brackets, exits 2
    and writes nothing."""
    (tmp_path / "typo.toml").write_text(TYPO)
    assert _refused(tmp_path, "simulate", "typo.toml", "--cycles", "10", "--out", "x.bin") == [
        "error: typo.toml [histogram]: unknown section (known: laser, sensor, gate, "
        "atmosphere, [[targets]], [[ambient]])",
        "error: typo.toml [gate] t_laser_win_ns: expected a finite number, found text 'abc'",
        "error: typo.toml [[targets]] #1 colour: unknown key (known: "
        + ", ".join(_target_keys()) + ")",
        "error: typo.toml [[targets]] #1 pixels: [0, 300] outside 0..127 (first <= last)"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["typo.toml"]


def _target_keys():
    import dataclasses

    from stages.models.scene import Target

    return [f.name for f in dataclasses.fields(Target)]


def test_a_chip_capture_given_as_linospad2_is_refused(tmp_path):
    """--format linospad2 on this project's capture: exit 2, the likely format named,
    nothing written; a real LinoSPAD2 file with the same option passes the check."""
    from pipeline.cli.instruments import refuse_if_not
    from pipeline.io.capture import CaptureWriter
    from stages.testpattern import pattern_words

    words, _ = pattern_words(2000, 128, hit_prob=0.05, peak_code=300.0, rng=1)
    with CaptureWriter(tmp_path / "chip", 128, kind="pattern") as w:
        w.write(words)
    assert _refused(tmp_path, "histogram", "chip.bin", "--format", "linospad2", "--out",
                    "h.parquet") == [
        "error: chip.bin: not a LinoSPAD2 file: 1235 of its first 1235 lines have invalid "
        "words before valid ones, which that format never has; its content reads as a "
        "tcspc file: give --format tcspc or leave --format out; nothing written"]
    assert not (tmp_path / "h.parquet").exists()
    real = Path(__file__).parents[2] / "data" / "linospad2" / "test_data_2212b.dat"
    refuse_if_not(str(real), "linospad2")  # no error


def test_no_markup_tags_in_printed_text():
    """The consoles print with markup off, so a rich tag in a message would be printed
    as it is ("[yellow]warning:[/yellow]"): colour goes through warn, note and error."""
    tag = re.compile(r"\[/?(bold|italic|yellow|red|green|blue|cyan|magenta|dim)( [a-z]+)?\]")
    root = CLI.parents[1]
    found = [f"{p.relative_to(root)}:{n}" for d in ("pipeline", "flows")
             for p in sorted((root / d).rglob("*.py"))
             for n, line in enumerate(p.read_text().splitlines(), 1) if tag.search(line)]
    assert not found, f"rich markup in printed text (use pipeline.cli.console): {found}"
