"""docs/cli.md, written from the click commands themselves (``make docs``).

Every command's ``--help`` text, in the order ``tcspc --help`` lists them, groups first
followed by their subcommands. A test fails when docs/cli.md drifts from the code.
"""

from __future__ import annotations

import click

WIDTH = 100  #: help text width in the generated page (independent of the terminal)


def _walk(cmd: click.Command, ctx: click.Context, path: list[str]):
    yield path, cmd, ctx
    if isinstance(cmd, click.Group):
        for name in cmd.list_commands(ctx):
            sub = cmd.get_command(ctx, name)
            if sub is None or sub.hidden:
                continue
            sub = getattr(sub, "_load", lambda s=sub: s)()  # a lazily loaded entry point
            sub_ctx = click.Context(sub, info_name=name, parent=ctx, max_content_width=WIDTH,
                                    terminal_width=WIDTH)
            yield from _walk(sub, sub_ctx, [*path, name])


def cli_markdown(group: click.Group | None = None, prog: str = "tcspc") -> str:
    """The markdown reference of every command under ``group`` (default: ``tcspc``)."""
    if group is None:
        from pipeline.cli.app import cli as group
    root = click.Context(group, info_name=prog, max_content_width=WIDTH, terminal_width=WIDTH,
                         **group.context_settings)
    lines = ["# Command-line reference", "",
             "Generated from the commands' own help by `make docs` "
             "(`python -m pipeline.cli.docs > docs/cli.md`); a test fails when it drifts. "
             "Each command also answers `--help`.", ""]
    for path, cmd, ctx in _walk(group, root, [prog]):
        lines += [f"{'#' * min(len(path) + 1, 4)} `{' '.join(path)}`", "", "```text",
                  cmd.get_help(ctx).rstrip(), "```", ""]
    return "\n".join(lines)


if __name__ == "__main__":  # pragma: no cover - exercised through `make docs`
    print(cli_markdown(), end="")
