"""The ``soulctl`` Typer application and its entry point, which keeps the exit-status
contract of the README for every command:

* 0 success;
* 2 bad input: one line on stderr naming the problem and the accepted range; no output file
  is written or changed (every command runs inside ``files.staged_outputs``, committed only
  on 0 and 3);
* 3 an unstable loop (``filter analyze``: figures still printed; ``loop run``: the simulated
  loop diverged, or the safety net of its auxiliary loops could not recover it, its telemetry
  still written; ``optimize gains``: the same, no gain file written);
* 130 / 143 interrupted by SIGINT (Ctrl-C) / SIGTERM: one line, no output written, the
  temporaries removed;
* 141 the reader of stdout went away (`soulctl ... | head -1`): the outputs are written;
* 1 an unexpected failure: a bug (its traceback is printed), or the system failing under the
  command (e.g. a full disk: one line).
"""

from __future__ import annotations

import os
import signal
import sys
import warnings

import typer
from typer.core import TyperGroup

from .. import __version__
from ..errors import InputError
from ..files import staged_outputs
from .help import polish
from .output import ascii_fallback
from .progress import REQUESTED

# The commands, each in its module and imported only when it runs or shows its own help, so
# that the CLI starts at once (`soulctl --version`, `--help`) and a command pays only for the
# physics it uses: name -> (module, attribute: a typer.Typer group or a command function,
# the one-line summary `soulctl --help` lists; tests/cli/test_startup.py holds it to the
# command's own help).
COMMANDS: dict[str, tuple[str, str, str]] = {
    "configure": ("configure", "configure", "Set up an observation for a guide star of R magnitude from the SOUL look-up table."),
    "filter": ("filter", "app", "Analyse and design temporal control filters (margins, rejection, the Tip/Tilt IIR design)."),
    "optics": ("optics", "app", "Optical models: turbulence, calibration, optical gains."),
    "loop": ("loop", "app", "The simulated closed loop."),
    "optimize": ("optimize", "app", "Gain optimisation: trial-and-error, MGM, OGTL."),
    "telemetry": ("telemetry", "app", "Loop telemetry: inspect, spectra, conversion between formats, plant identification."),
    "rtc": ("rtc", "app", "Real-time computer parameter sets: the checks before an upload."),
    "sweep": ("sweep", "sweep", "Run a grid of simulated closed loops as Dask tasks, one row per case."),
}


def load_command(name: str):
    """The click command of ``name``, its module imported now."""
    import importlib

    module, attribute, _ = COMMANDS[name]
    target = getattr(importlib.import_module(f"{__package__}.{module}"), attribute)
    holder = typer.Typer(add_completion=False, pretty_exceptions_enable=False)
    if isinstance(target, typer.Typer):  # a group, kept a group even with one command
        holder.add_typer(target, name=name)
        command = typer.main.get_command(holder).commands[name]  # type: ignore[attr-defined]
    else:
        holder.command(name=name)(target)  # a command function: a one-command app is that command
        command = typer.main.get_command(holder)
    polish(command)
    return command


class _LazyGroup(TyperGroup):
    """soulctl's top level: its commands listed from ``COMMANDS`` and imported when used."""

    _listing = False

    def list_commands(self, ctx) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx, cmd_name: str):
        if cmd_name not in COMMANDS:
            return None
        if self._listing:  # the top-level help lists names and summaries only
            return typer.core.TyperCommand(name=cmd_name, help=COMMANDS[cmd_name][2])
        return load_command(cmd_name)

    def format_help(self, ctx, formatter) -> None:
        self._listing = True
        try:
            super().format_help(ctx, formatter)
        finally:
            self._listing = False


app = typer.Typer(
    name="soulctl",
    cls=_LazyGroup,
    help="Configure, simulate, analyse and tune the control of a pyramid-WFS SCAO system such as SOUL at the LBT.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"soulctl {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version and exit."),
    progress: bool = typer.Option(
        False,
        "--progress",
        help="Progress as plain lines on stderr when stderr is not a terminal (a log, CI); a terminal always shows it.",
    ),
) -> None:
    """soulctl: control engineering for a pyramid-WFS SCAO system (SOUL at the LBT)."""
    if progress:
        REQUESTED.set(True)


def _fail(message: str, status: int = 2) -> int:
    # One line, whatever the message held.
    print("soulctl: error: " + " ".join(str(message).split()), file=sys.stderr)
    return status


def _status_of_cli_exception(e: Exception) -> int | None:
    """Exit status for the command-line framework's own exceptions (click's, or the click that
    recent typer releases vendor), or None if ``e`` is not one of them."""
    name = type(e).__name__
    if name == "NoArgsIsHelpError":  # `soulctl` alone: the help, and success
        # The error holds the help as text; a rich formatter has printed it already and holds "".
        if e.format_message():  # type: ignore[attr-defined]
            typer.echo(e.format_message())  # type: ignore[attr-defined]
        return 0
    if name == "Exit" and hasattr(e, "exit_code"):  # --help, --version
        return e.exit_code
    if name == "Abort":
        return _fail("aborted", 130)
    if name == "BadParameter" and getattr(e, "param", None) is not None and e.param.opts:  # type: ignore[attr-defined]
        # a value the option's parser refused: in the words of every other check ("--wind must be in ...")
        return _fail(f"{e.param.opts[0]} {e.message}", 2)  # type: ignore[attr-defined]
    if hasattr(e, "format_message") and hasattr(e, "exit_code"):  # usage errors: bad option, missing value
        return _fail(e.format_message(), 2)
    return None


class Interrupted(BaseException):
    """SIGINT or SIGTERM, raised where the program is so that every clean-up runs.  Not a
    KeyboardInterrupt: the command-line framework would turn that into its own 'Abort'."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


class _Signals:
    """The interrupt handler of one command: raises ``Interrupted`` and remembers the signal,
    since an exception raised while Python runs a finaliser or a weakref callback (h5py closing
    a file, say) is printed and dropped instead of propagated; ``check`` raises it again before
    anything is committed."""

    def __init__(self) -> None:
        self.pending: int | None = None

    def __call__(self, signum, frame) -> None:
        self.pending = signum
        raise Interrupted(signum)

    def check(self) -> None:
        if self.pending is not None:
            raise Interrupted(self.pending)


INTERRUPT_STATUS = {signal.SIGINT: (130, "Ctrl-C"), signal.SIGTERM: (143, "SIGTERM")}
DISCARDED = "outputs discarded (a telemetry file being streamed is kept, marked partial; a sweep keeps its finished rows for --resume)"
BROKEN_PIPE = 141  # 128 + SIGPIPE, as shell tools report a reader that went away


def _run(argv: list[str] | None, signals: _Signals) -> int:
    """Run the command inside staged outputs: committed on exit status 0 and 3 only (and when
    the reader of stdout went away after the work was done: the files are complete)."""
    requested = REQUESTED.set(False)
    try:
        return _run_staged(argv, signals)
    finally:
        REQUESTED.reset(requested)


def _run_staged(argv: list[str] | None, signals: _Signals) -> int:
    with staged_outputs() as stage, warnings.catch_warnings():
        # Third-party warnings (numpy casts, matplotlib's cache, Dask's ports) are not the
        # user's business and would break the one-line refusal: stderr is soulctl's own.
        warnings.simplefilter("ignore")
        try:
            root = typer.main.get_command(app)
            polish(root)
            result = root.main(args=argv, prog_name="soulctl", standalone_mode=False)
            status = result if isinstance(result, int) else 0
        except BrokenPipeError:
            _silence_stdout()
            status = BROKEN_PIPE
        signals.check()
        if status in (0, 3, BROKEN_PIPE):
            stage.commit()
        return status


def _silence_stdout() -> None:
    """Point stdout at /dev/null so that the interpreter's final flush finds no broken pipe."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # stdout without a file descriptor (tests)
        pass


def main(argv: list[str] | None = None) -> int:
    """Entry point of the console script.  With argv None (the console script) it exits the
    process; with an explicit argv (tests) it returns the exit status."""
    ascii_fallback()
    signals = _Signals()
    previous = {n: signal.signal(n, signals) for n in INTERRUPT_STATUS} if _main_thread() else {}
    try:
        status = _run(argv, signals)
    except InputError as e:
        status = _fail(str(e))
    except Interrupted as e:
        code, name = INTERRUPT_STATUS[signal.Signals(e.signum)]
        status = _fail(f"interrupted ({name}); {DISCARDED}", code)
    except KeyboardInterrupt:  # a SIGINT outside the handler (another thread's handler)
        status = _fail(f"interrupted (Ctrl-C); {DISCARDED}", 130)
    except OSError as e:  # the system failing under the command (a full disk): one line, not a traceback
        status = _fail(f"{e.strerror or e}", 1)
    except Exception as e:
        cli_status = _status_of_cli_exception(e)
        if cli_status is None:
            raise
        status = cli_status
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
