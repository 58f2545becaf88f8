"""Input files: the one check every reader makes first."""
from __future__ import annotations

from pathlib import Path

from statfit.errors import StatfitError


def existing_file(path: str | Path, what: str) -> Path:
    """``path`` as a Path when it names a readable file; otherwise one message saying whether it
    is missing, a folder, or too long a name (``what`` names the file: "scan", "camera file")."""
    path = Path(path)
    try:
        if path.is_dir():
            raise StatfitError(f"{what} {path} is a folder, not a file")
        if not path.is_file():
            raise StatfitError(f"{what} not found: {path}")
    except OSError as exc:  # e.g. a name longer than the system allows
        raise StatfitError(f"{what} {str(path)[:80]}…: {exc.strerror}") from None
    return path
