"""Exceptions that carry a message meant for the user (the CLI prints it as one line, exit 2)."""


class StatfitError(Exception):
    """Bad input or an unusable configuration; the message is shown to the user as is."""


class DivergenceError(StatfitError):
    """The fit produced a non-finite loss or vertex position."""


class StatfitWarning(UserWarning):
    """Something the user should know that does not stop the fit."""


def one_line(error: BaseException) -> str:
    """A failure as the one line a fit that goes on without it records: a StatfitError's message, else
    its type and the first line of its message."""
    if isinstance(error, StatfitError):
        return str(error)
    if isinstance(error, MemoryError):
        return "out of memory"
    return f"{type(error).__name__}: {error}".splitlines()[0]
