"""The ``soulctl`` Typer application and its entry point.

Exit status: 0 success; 2 bad input (one line on stderr naming the problem and the accepted
range, nothing written); 3 the loop is unstable (``filter analyze``: figures still printed; ``loop run``: the simulated
loop diverged, telemetry still written; ``optimize gains``: the loop diverged, no gain file written;
``sweep`` returns 0 once every case has a row, failed or not);
1 an unexpected internal error.
"""

from __future__ import annotations

import sys

import typer

from .. import __version__
from ..errors import InputError
from . import configure
from . import filter as filter_cli
from . import loop as loop_cli
from . import optics as optics_cli
from . import optimize as optimize_cli
from .sweep import sweep

app = typer.Typer(
    name="soulctl",
    help="Configure, simulate, analyse and tune the control of a pyramid-WFS SCAO system such as SOUL at the LBT.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
app.command(name="configure")(configure.configure)
app.add_typer(filter_cli.app, name="filter")
app.add_typer(optics_cli.app, name="optics")
app.add_typer(loop_cli.app, name="loop")
app.add_typer(optimize_cli.app, name="optimize")
app.command(name="sweep")(sweep)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"soulctl {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version and exit."),
) -> None:
    """soulctl: control engineering for a pyramid-WFS SCAO system (SOUL at the LBT)."""


def _fail(message: str, status: int = 2) -> int:
    # One line, whatever the message held.
    print("soulctl: error: " + " ".join(str(message).split()), file=sys.stderr)
    return status


def _status_of_cli_exception(e: Exception) -> int | None:
    """Exit status for the command-line framework's own exceptions (click's, or the click that
    recent typer releases vendor), or None if ``e`` is not one of them."""
    name = type(e).__name__
    if name == "NoArgsIsHelpError":  # `soulctl` alone: the help, and success
        typer.echo(e.ctx.get_help())
        return 0
    if name == "Exit" and hasattr(e, "exit_code"):  # --help, --version
        return e.exit_code
    if name == "Abort":
        return _fail("aborted", 130)
    if hasattr(e, "format_message") and hasattr(e, "exit_code"):  # usage errors: bad option, missing value
        return _fail(e.format_message(), 2)
    return None


def main(argv: list[str] | None = None) -> int:
    """Entry point of the console script.  With argv None (the console script) it exits the
    process; with an explicit argv (tests) it returns the exit status."""
    try:
        result = app(args=argv, prog_name="soulctl", standalone_mode=False)
        status = result if isinstance(result, int) else 0
    except InputError as e:
        status = _fail(str(e))
    except KeyboardInterrupt:
        status = _fail("interrupted", 130)
    except BrokenPipeError:
        status = 1  # the reader went away (e.g. `soulctl ... | head`): nothing to say
    except OSError as e:  # e.g. stdout on a full disk: one line, not a traceback
        status = _fail(f"{e.strerror or e}", 1)
    except Exception as e:
        status = _status_of_cli_exception(e)
        if status is None:
            raise
    if argv is None:
        sys.exit(status)
    return status


if __name__ == "__main__":
    main()
