"""The ``soulctl`` Typer application and its entry point, which keeps the exit-status
contract of the README for every command:

* 0 success;
* 2 bad input: one line on stderr naming the problem and the accepted range; no output file
  is written or changed (every command runs inside ``files.staged_outputs``, committed only
  on 0 and 3);
* 3 an unstable loop (``filter analyze``: figures still printed; ``loop run``: the simulated
  loop diverged, its telemetry still written; ``optimize gains``: the loop diverged, no gain
  file written);
* 130 / 143 interrupted by SIGINT (Ctrl-C) / SIGTERM: one line, no output written, the
  temporaries removed;
* 1 an unexpected internal error (a bug: its traceback is printed).
"""

from __future__ import annotations

import signal
import sys

import typer

from .. import __version__
from ..errors import InputError
from ..files import staged_outputs
from . import configure
from . import filter as filter_cli
from . import loop as loop_cli
from . import optics as optics_cli
from . import optimize as optimize_cli
from .output import ascii_fallback
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


class Interrupted(BaseException):
    """SIGINT or SIGTERM, raised where the program is so that every clean-up runs.  Not a
    KeyboardInterrupt: the command-line framework would turn that into its own 'Abort'."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _interrupt(signum, frame) -> None:
    raise Interrupted(signum)


INTERRUPT_STATUS = {signal.SIGINT: (130, "Ctrl-C"), signal.SIGTERM: (143, "SIGTERM")}
DISCARDED = "outputs discarded (a sweep keeps its finished rows for --resume)"


def _run(argv: list[str] | None) -> int:
    """Run the command inside staged outputs: committed on exit status 0 and 3 only."""
    with staged_outputs() as stage:
        result = app(args=argv, prog_name="soulctl", standalone_mode=False)
        status = result if isinstance(result, int) else 0
        if status in (0, 3):
            stage.commit()
        return status


def main(argv: list[str] | None = None) -> int:
    """Entry point of the console script.  With argv None (the console script) it exits the
    process; with an explicit argv (tests) it returns the exit status."""
    ascii_fallback()
    previous = {n: signal.signal(n, _interrupt) for n in INTERRUPT_STATUS} if _main_thread() else {}
    try:
        status = _run(argv)
    except InputError as e:
        status = _fail(str(e))
    except Interrupted as e:
        code, name = INTERRUPT_STATUS[e.signum]
        status = _fail(f"interrupted ({name}); {DISCARDED}", code)
    except KeyboardInterrupt:  # a SIGINT outside the handler (another thread's handler)
        status = _fail(f"interrupted (Ctrl-C); {DISCARDED}", 130)
    except BrokenPipeError:
        status = 1  # the reader went away (e.g. `soulctl ... | head`): nothing to say
    except OSError as e:  # e.g. stdout on a full disk: one line, not a traceback
        status = _fail(f"{e.strerror or e}", 1)
    except Exception as e:
        status = _status_of_cli_exception(e)
        if status is None:
            raise
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    if argv is None:
        sys.exit(status)
    return status


def _main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


if __name__ == "__main__":
    main()
