"""Exceptions that carry a message meant for the user (the CLI prints it as one line, exit 2)."""


class StatfitError(Exception):
    """Bad input or an unusable configuration; the message is shown to the user as is."""


class DivergenceError(StatfitError):
    """The fit produced a non-finite loss or vertex position."""


class StatfitWarning(UserWarning):
    """Something the user should know that does not stop the fit."""
