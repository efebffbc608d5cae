"""The command line's two consoles and its error printer, in one module every command uses.

Markup is off: what a command prints is user text (paths, TOML sections such as
``[histogram]``, journal ranges such as ``[0, 4096)``) and rich's markup would swallow the
bracketed parts. Colour is given by style, never by markup in the text: :func:`warn`,
:func:`note` and :func:`error` colour their label and print the message as it is.
"""

from __future__ import annotations

import sys

import click


def console(stderr: bool = False):
    """A rich console that wraps lines only on a terminal: piped or captured, one message
    stays one line (logs are grepped; a path longer than 80 columns must not split a
    sentence). Markup is off (see the module's docstring)."""
    from rich.console import Console

    stream = sys.stderr if stderr else sys.stdout
    return Console(stderr=stderr, soft_wrap=not stream.isatty(), markup=False)


class _FirstUse:
    """:func:`console`, made when first used: rich.console's import (25-30 ms) is paid by
    the commands that print, not by a quiet `tcspc histogram` or `tcspc --help`."""

    def __init__(self, stderr: bool = False) -> None:
        self._stderr, self._console = stderr, None

    def get(self):
        if self._console is None:
            self._console = console(self._stderr)
        return self._console

    def __getattr__(self, name):
        return getattr(self.get(), name)


err = _FirstUse(stderr=True)
out = _FirstUse()


def _labelled(label: str, style: str, message: str, con=err) -> None:
    from rich.text import Text

    con.print(Text.assemble((label, style), " ", str(message)), highlight=False,
              soft_wrap=True)


def warn(message: str, con=err) -> None:
    """``warning: MESSAGE`` on stderr, the label in yellow, the message as given."""
    _labelled("warning:", "yellow", message, con)


def note(message: str, con=err) -> None:
    """``note: MESSAGE`` on stderr, the label in yellow, the message as given."""
    _labelled("note:", "yellow", message, con)


def error(message: str, con=err) -> None:
    """``error: MESSAGE`` on stderr, the label in red, the message as given; a message of
    several lines (a config's problems, one a line) gets the label on each line."""
    for line in str(message).splitlines() or [""]:
        _labelled("error:", "red", line, con)


class InternalError(click.ClickException):
    """A bug, not the user's input (word classes that do not add up to the words read):
    exit status 1, the one status the contract keeps for internal errors."""

    exit_code = 1


class Incomplete(click.ClickException):
    """A result written (or refused) as incomplete: an input cut short, a check of the
    result that failed, a run that does not balance: exit status 3."""

    exit_code = 3
