"""Point clouds as text, the way scanners and their software export them (``.xyz``, ``.asc``,
``.csv``, ``.txt``): one point a row, its first three numbers ``x y z``; the rest of a row
(normals, colours, intensity) is not read. Numbers are separated by whitespace, commas or
semicolons (as the first point's row has them); ``#`` and ``//`` start comments, and one header
row of names (``X,Y,Z,Nx,Ny,Nz``) may come before the points. Parsed by NumPy's C reader
(``numpy.loadtxt``): a million points (64 MB) in ~0.9 s on one core (docs/benchmarks.md §11).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from statfit.errors import StatfitError
from statfit.io.files import POINT_TEXT_SUFFIXES

COMMENTS = ("#", "//")
# Where the first point's row must start: comments, blank rows and one header row come first.
SNIFF_BYTES = 1 << 16


def read_point_text(path: Path, head: bytes) -> np.ndarray:
    """Points (M, 3) float64 of the text point cloud at ``path``; ``head``: its first bytes (at
    least :data:`SNIFF_BYTES` or the whole file), where the first point's row is looked for."""
    skip, delimiter = _layout(head, path)
    try:
        points = np.loadtxt(path, dtype=np.float64, comments=COMMENTS, delimiter=delimiter, skiprows=skip,
                            usecols=(0, 1, 2), ndmin=2, encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise _not_text(path) from None
    except ValueError as error:
        raise StatfitError(f"{path}: {_first_bad_row(path, skip, delimiter) or error}") from None
    return points


def point_text_bytes(points: np.ndarray, suffix: str) -> bytes:
    """Points (M, 3) as text rows ``x y z`` (``.csv``: ``x,y,z`` under a header row), each number
    with the 17 significant digits that read back to the same float64."""
    if suffix not in POINT_TEXT_SUFFIXES:
        raise StatfitError(f"a text point cloud is {', '.join(POINT_TEXT_SUFFIXES)}, not {suffix}")
    comma = suffix == ".csv"
    rows = np.char.mod("%.17g", np.asarray(points, dtype=np.float64))
    lines = [(",".join(row) if comma else " ".join(row)) for row in rows.tolist()]
    return (("x,y,z\n" if comma else "") + "\n".join(lines) + "\n").encode()


def _layout(head: bytes, path: Path) -> tuple[int, str | None]:
    """The rows before the first point's (comments, blanks, at most one header) and the delimiter
    of that row (None: whitespace)."""
    try:
        lines = head.decode("utf-8-sig").splitlines()
    except UnicodeDecodeError as error:
        if error.start < len(head) - 4:     # not a character cut in two at the end of the head
            raise _not_text(path) from None
        lines = head[:error.start].decode("utf-8-sig").splitlines()
    header = None
    for index, line in enumerate(lines[:-1] if len(head) >= SNIFF_BYTES else lines):
        text = _without_comments(line)
        if not text.strip():
            continue
        delimiter = ";" if ";" in text else "," if "," in text else None
        if _starts_with_three_numbers(text, delimiter):
            return index, delimiter
        if header is not None:
            raise StatfitError(f"{path}: row {index + 1} is not a point (x y z): {line.strip()[:60]!r}")
        header = index
    if header is not None:
        raise StatfitError(f"{path}: no row starts with three numbers x y z (row {header + 1}: "
                           f"{lines[header].strip()[:60]!r})")
    raise StatfitError(f"{path} contains no points")


def _not_text(path: Path) -> StatfitError:
    return StatfitError(f"{path} is not text: a point cloud in {path.suffix} is rows of numbers (x y z)")


def _starts_with_three_numbers(text: str, delimiter: str | None) -> bool:
    """Whether the row ``text`` (comments removed) starts with three numbers."""
    fields = text.split(delimiter)
    if len(fields) < 3:
        return False
    try:
        [float(field) for field in fields[:3]]
    except ValueError:
        return False
    return True


def _first_bad_row(path: Path, skip: int, delimiter: str | None) -> str | None:
    """Which row (counted from 1, comments included) of the file does not start with three
    numbers, and its text; read again only when NumPy refused the file (its row numbers leave out
    the rows skipped)."""
    with open(path, encoding="utf-8-sig", errors="replace") as rows:
        for number, line in enumerate(rows, start=1):
            text = _without_comments(line)
            if number > skip and text.strip() and not _starts_with_three_numbers(text, delimiter):
                return f"row {number} does not start with three numbers x y z: {line.strip()[:60]!r}"
    return None


def _without_comments(line: str) -> str:
    """``line`` up to its first comment mark."""
    for mark in COMMENTS:
        line = line.split(mark, 1)[0]
    return line
