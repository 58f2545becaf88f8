"""Landmark files: scan landmarks (one 3D point per model landmark, in the model's order, missing
ones NaN) as text rows ``x y z``, an iBUG-style ``.pts`` file (3D points between braces), or a
JSON list of ``[x, y, z]`` (``null`` for a missing one); and model landmark vertex indices (L
integers, text)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from statfit.errors import StatfitError
from statfit.io.files import existing_file


def _numbers(path: str | Path, what: str) -> list[list[str]]:
    """The non-empty rows of a whitespace- or comma-separated text file, ``#`` starting a comment."""
    path = existing_file(path, "landmark file")
    try:
        text = path.read_text().replace(",", " ")
    except (UnicodeDecodeError, OSError):
        raise StatfitError(f"{path}: {what}") from None
    return [row for row in (line.split("#")[0].split() for line in text.splitlines()) if row]


# No landmark file of any real use is larger (68 points of text are ~3 kB).
MAX_LANDMARK_BYTES = 1 << 20


def read_landmarks(path: str | Path) -> np.ndarray:
    """Points (L, 3); ``nan`` marks a missing landmark. ``.pts`` and ``.json`` by their suffix, else text."""
    path = existing_file(path, "landmark file")
    if path.stat().st_size > MAX_LANDMARK_BYTES:
        raise StatfitError(f"{path}: {path.stat().st_size} bytes is too large for a landmark file")
    suffix = path.suffix.lower()
    what = ("landmarks must be " + {".pts": "3D points (x y z) between { and } after a n_points: line",
                                     ".json": "a JSON list of [x, y, z] (null for a missing one)"}.get(
        suffix, "rows of three numbers (x y z; nan for a missing one)"))
    try:
        rows = _pts_rows(path, what) if suffix == ".pts" else _json_rows(path, what) if suffix == ".json" \
            else _numbers(path, what)
        points = np.array(rows, dtype=np.float64)
    except (ValueError, TypeError):  # ragged rows, text, nested lists
        raise StatfitError(f"{path}: {what}") from None
    if points.ndim != 2 or points.shape[1] != 3:
        raise StatfitError(f"{path}: {what}")
    if np.isinf(points).any():
        raise StatfitError(f"{path}: landmarks contain infinite values")
    return points


def _pts_rows(path: Path, what: str) -> list[list[str]]:
    """The rows between ``{`` and ``}`` of an iBUG ``.pts`` file, checked against its ``n_points``."""
    lines = [line.strip() for line in _text(path, what).splitlines()]
    header = {key.strip(): value.strip() for key, _, value in (line.partition(":") for line in lines if ":" in line)}
    if "{" not in lines or "}" not in lines or "n_points" not in header or not header["n_points"].isdigit():
        raise StatfitError(f"{path}: {what}")
    rows = [line.split() for line in lines[lines.index("{") + 1:lines.index("}")] if line]
    if len(rows) != int(header["n_points"]):
        raise StatfitError(f"{path}: n_points says {header['n_points']} but {len(rows)} points follow")
    if rows and all(len(row) == 2 for row in rows):
        raise StatfitError(f"{path}: 2D landmarks (image points); a scan needs 3D ones (x y z)")
    return rows


def _json_rows(path: Path, what: str) -> list:
    try:
        rows = json.loads(_text(path, what))
    except ValueError:
        raise StatfitError(f"{path}: not JSON; {what}") from None
    if not isinstance(rows, list):
        raise StatfitError(f"{path}: {what}")
    return [[np.nan] * 3 if row is None else row for row in rows]


def _text(path: Path, what: str) -> str:
    try:
        return path.read_text()
    except (UnicodeDecodeError, OSError):
        raise StatfitError(f"{path}: {what}") from None


def read_landmark_indices(path: str | Path) -> np.ndarray:
    """Vertex indices (L,), in landmark order (any number per row)."""
    what = "landmark indices must be non-negative integers"
    tokens = [token for row in _numbers(path, what) for token in row]
    if not tokens or not all(token.isdigit() for token in tokens):
        raise StatfitError(f"{path}: {what}")
    return np.array(tokens, dtype=np.int64)


def landmarks_text(points: np.ndarray) -> str:
    """Landmarks (L, 3) as the text format ``read_landmarks`` reads: one ``x y z`` row each."""
    return "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in np.asarray(points, dtype=np.float64).tolist())
