"""How every command's ``--help`` reads: one pass over a command's click tree, applied where
``app.load_command`` builds it, so that the rules hold for every command without each
declaration repeating them:

* a flag shows no type (Typer would print ``<bool>``), a value its name or kind (``N``, ``X``),
  a choice its values (declared with the option);
* a default given as text reads ``[default: 1.0]``, not ``[default: (1.0)]``;
* help text is plain text: brackets such as ``[misregistration]`` are not markup;
* options sit in panels by what they set (``PANELS``: observation, atmosphere, control,
  pyramid, auxiliary loops, output), so that a long command reads one panel at a time;
* a command's summary in its group's listing is the first paragraph of its help, one line.
"""

from __future__ import annotations

from rich.markup import escape

# Option -> panel, for every command that has the option (one table: the options a loop has
# are shared by `loop run`, `optimize gains`, `rtc check` and `sweep`).  Options not listed
# stay in the command's "Options" panel.
_PANEL_OPTIONS = {
    "Observation": "--config --mag --plant --duration --band --seed --no-noise --rate --frame-rate",
    "Atmosphere and telescope": "--seeing --wind --L0 --vibrations --no-vibrations --no-resonance --resonance",
    "Control": "--tt-control --gains --allow-unstable --ideal --method --chi-table --delay-frames",
    "Pyramid and calibration": "--oversampling --wfs-field --misregistration --no-cache --cache-dir",
    "Non-common-path aberration": "--ncpa --ncpa-offsets --ncpa-offset-fraction",
    "Auxiliary loops (MGM, OGTL)": "--mgm --ogtl --period --probe-mode --probe-amplitude --probe-frequency",
    "Output": "--telemetry --telemetry-fields --telemetry-every --plot --print-config --json --out",
}
PANELS = {option: panel for panel, options in _PANEL_OPTIONS.items() for option in options.split()}
_MIN_OPTIONS_FOR_PANELS = 12  # a shorter command reads in one panel
_METAVARS = {"int": "N", "float": "X", "Path": "PATH", "str": "TEXT"}  # a value's name by its type


def polish(command) -> None:
    """Apply the rules above to ``command`` and, for a group, to each of its commands."""
    _plain_help_option(command)
    if command.help:
        command.help = escape(command.help)
    params = [p for p in command.params if getattr(p, "param_type_name", "") == "option"]
    panelled = len(params) >= _MIN_OPTIONS_FOR_PANELS
    for param in params:
        _polish_option(param, panelled)
    for argument in (p for p in command.params if getattr(p, "param_type_name", "") == "argument"):
        if argument.metavar is not None:  # its name says what it is: no type beside it
            argument.display_type_rich = lambda ctx: None
        if argument.help:
            argument.help = escape(argument.help)
    for sub in getattr(command, "commands", {}).values():
        if sub.help and not sub.short_help:
            sub.short_help = escape(" ".join(sub.help.split("\n\n")[0].split()))
        polish(sub)


def _polish_option(param, panelled: bool) -> None:
    if param.is_flag:
        param.metavar = ""
    elif param.metavar is None:  # a value without a declared name: its kind, not Typer's <int>
        param.metavar = _METAVARS.get(param.bare_type(), "VALUE")
    if isinstance(param.show_default, str):
        param.help = f"{param.help or ''}  [default: {param.show_default}]".strip()
        param.show_default = False
    if param.help:
        param.help = escape(param.help)
    if panelled:
        panel = next((PANELS[o] for o in param.opts if o in PANELS), None)
        if panel is not None:
            param.rich_help_panel = panel


def _plain_help_option(command) -> None:
    """``--help`` is a flag like the others (click makes it anew for each context)."""
    make = command.get_help_option

    def get_help_option(ctx):
        option = make(ctx)
        if option is not None:
            option.metavar = ""
        return option

    command.get_help_option = get_help_option
