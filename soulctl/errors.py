"""Errors that reach the user as one line and exit status 2 (bad input), not as a traceback."""


class InputError(ValueError):
    """Invalid user input or configuration: the message names the problem and the accepted range."""
