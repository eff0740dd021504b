"""What every command of the ``mrft-tune`` command line shares: the typer app, the consoles.

Command modules import these from here (not from the package), so that the package,
which registers the commands, and the commands do not import each other.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

import typer
from rich.console import Console, ConsoleDimensions
from rich.spinner import Spinner
from rich.text import Text

__all__ = ["app", "console", "err_console", "styled", "heartbeat_spinner", "heartbeat_wait",
           "DECLINED", "PIPED_WIDTH"]

app = typer.Typer(
    name="mrft-tune",
    help=(
        "Tune a multirotor from take-off in seconds: relay tests (MRFT) on altitude, roll,\n"
        "pitch, then x and y; neural-network identification; PD gains written back over "
        "MAVLink.\n\n"
        "Start with:  mrft-tune demo   (tunes the bundled simulated vehicle, no hardware)."
    ),
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    # Plain help: rich markup mode would eat "[design]" in help texts and label flags <bool>.
    rich_markup_mode=None,
    context_settings={"max_content_width": 120},  # click's default wraps help at 80
)
#: exit code when the user answers no to a take-off or write question (as an interruption)
DECLINED = 130

#: columns of output that is not a terminal (a pipe, a file) and has no COLUMNS: wide enough
#: that a table row or a note stays on one line for grep and for scripts
PIPED_WIDTH = 1000


class _Console(Console):
    """A rich console that cuts nothing when its output is a pipe or a file."""

    @property
    def size(self) -> ConsoleDimensions:
        size = super().size
        if self._width is None and not self.is_terminal and "COLUMNS" not in os.environ:
            return ConsoleDimensions(PIPED_WIDTH, size.height)
        return size

    @size.setter
    def size(self, new_size: tuple[int, int]) -> None:
        self._width, self._height = new_size


#: Markup is off: notes, errors, paths and table cells carry user text with square brackets
#: ("[[vehicle]]", ".[design]"); styled words are built as :class:`rich.text.Text`.
console = _Console(markup=False)
err_console = _Console(stderr=True, markup=False)


def styled(text: str, style: str) -> Text:
    """``text`` in ``style`` (markup is off on both consoles, so style with this)."""
    return Text(text, style=style)


def heartbeat_wait_text(connect: str, timeout_s: float) -> str:
    return f"connecting to {connect}: waiting up to {timeout_s:g} s for a vehicle heartbeat"


def heartbeat_spinner(connect: str, timeout_s: float) -> Spinner:
    """What a live display shows until the vehicle answers. Where the display is not a
    terminal (nothing live is drawn there), the wait is said once on stderr instead."""
    text = heartbeat_wait_text(connect, timeout_s)
    if not console.is_terminal:
        err_console.print(text + " ...", highlight=False, soft_wrap=True)
    return Spinner("dots", text=text)


@contextmanager
def heartbeat_wait(connect: str, timeout_s: float) -> Iterator[None]:
    """A spinner on stderr while a command connects (one line where stderr is no terminal)."""
    text = heartbeat_wait_text(connect, timeout_s)
    if err_console.is_terminal:
        with err_console.status(text):
            yield
    else:
        err_console.print(text + " ...", highlight=False, soft_wrap=True)
        yield
