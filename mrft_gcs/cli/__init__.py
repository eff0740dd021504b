"""The ``mrft-tune`` command line: thin typer commands over the library.

Each command group lives in its own module here and registers on :data:`app`
(:mod:`mrft_gcs.cli.app`, with the consoles the commands share).
Library errors (:class:`mrft_gcs.errors.MrftError`) become a one-line message
and an exit code in exactly one place: :func:`main`.
"""

from __future__ import annotations

import sys

from rich.text import Text

from mrft_gcs.cli.app import (
    DECLINED,
    PIPED_WIDTH,
    app,
    console,
    err_console,
    heartbeat_spinner,
    heartbeat_wait,
    styled,
)
from mrft_gcs.errors import MrftError

__all__ = ["app", "main", "console", "err_console", "styled", "heartbeat_spinner",
           "heartbeat_wait", "DECLINED", "PIPED_WIDTH"]


def _error_line(message: str) -> Text:
    return Text.assemble(("error:", "bold red"), " ", message)


def _register() -> None:
    # Imported for their side effect of adding commands to ``app``.
    from mrft_gcs.cli import commands  # noqa: F401


def main(argv: list[str] | None = None) -> int:
    """Entry point of the console script; returns the process exit code."""
    _register()
    try:
        # a typer.Exit(n) comes back as n
        code = app(args=argv, prog_name="mrft-tune", standalone_mode=False)
    except MrftError as err:
        err_console.print(_error_line(str(err)), highlight=False, soft_wrap=True)
        return err.exit_code
    except KeyboardInterrupt:
        err_console.print(styled("interrupted", "bold red"))
        return 130
    except SystemExit as exc:  # typer/click usage errors
        return int(exc.code or 0)
    except Exception as exc:
        # Click's own exceptions (typer vendors click, so match by behaviour, not class).
        name = type(exc).__name__
        if name == "Exit":
            return int(getattr(exc, "exit_code", 0))
        if name == "Abort":
            err_console.print(styled("aborted", "bold red"))
            return 130
        if hasattr(exc, "show") and hasattr(exc, "exit_code"):
            exc.show()
            return int(exc.exit_code)
        raise
    return code if isinstance(code, int) else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
