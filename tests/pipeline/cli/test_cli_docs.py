"""docs/cli.md is written from the click commands (`make docs`); it must not drift."""

from pathlib import Path

from pipeline.cli.docs import cli_markdown

DOCS = Path(__file__).parents[3] / "docs" / "cli.md"


def test_cli_reference_does_not_drift():
    assert DOCS.read_text() == cli_markdown(), "docs/cli.md is stale: run `make docs`"


def test_cli_reference_covers_every_command():
    text = cli_markdown()
    for cmd in ("tcspc calibrate delay", "tcspc range", "tcspc stage sink", "tcspc flow run",
                "tcspc model predict", "tcspc daemon"):
        assert f"`{cmd}`" in text
