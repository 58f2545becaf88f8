"""Splats bound to a mesh (:class:`statfit.renderer.MeshSplats`) in and out, as a binary
little-endian PLY that generic point viewers open as a coloured point cloud.

One ``vertex`` element per splat, float32 unless said: ``x y z`` the world centre on the mesh it
was saved with, ``nx ny nz`` its unit normal (tangent_u × tangent_v); the binding, which is what
is read back: ``triangle`` (int32), ``bary_0 bary_1 bary_2``, ``angle``, ``log_scale_0
log_scale_1``; ``f_red f_green f_blue`` and ``opacity`` the sigmoids of the logits, in [0, 1].
The header comment ``statfit splats bound to a mesh of F faces`` ties the file to its mesh.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from statfit.errors import StatfitError
from statfit.io.files import existing_file
from statfit.io.mesh import HEADER_BYTES, MAX_FILE_BYTES

FLOAT, INT = "<f4", "<i4"
PROPERTIES = (("x", FLOAT), ("y", FLOAT), ("z", FLOAT), ("nx", FLOAT), ("ny", FLOAT), ("nz", FLOAT),
              ("triangle", INT), ("bary_0", FLOAT), ("bary_1", FLOAT), ("bary_2", FLOAT), ("angle", FLOAT),
              ("log_scale_0", FLOAT), ("log_scale_1", FLOAT), ("f_red", FLOAT), ("f_green", FLOAT),
              ("f_blue", FLOAT), ("opacity", FLOAT))
RECORD = np.dtype(list(PROPERTIES))
PROPERTY_LINES = [f"property {'int' if kind == INT else 'float'} {name}" for name, kind in PROPERTIES]
FORMAT_LINE = "format binary_little_endian 1.0"
COMMENT = "comment statfit splats bound to a mesh of {} faces"
COLOURS = ("f_red", "f_green", "f_blue")


def splats_bytes(records: np.ndarray, faces: int) -> bytes:
    """The PLY of splat ``records`` (P,) of dtype :data:`RECORD`, bound to a mesh of ``faces`` faces."""
    if records.dtype != RECORD:
        raise StatfitError(f"splat records must have the dtype {RECORD}, got {records.dtype}")
    return _header(len(records), faces).encode("ascii") + records.tobytes()


def _header(count: int, faces: int) -> str:
    """The PLY header of ``count`` splats on a mesh of ``faces`` faces, ``end_header`` line included."""
    lines = ["ply", FORMAT_LINE, COMMENT.format(faces), f"element vertex {count}"]
    return "\n".join(lines + PROPERTY_LINES + ["end_header"]) + "\n"


def read_splats(path: str | Path, faces: int) -> np.ndarray:
    """The checked records (P,) of dtype :data:`RECORD` of a file written by :func:`splats_bytes`
    for a mesh of ``faces`` faces (the file must say as many)."""
    path = existing_file(path, "splat file")
    size = path.stat().st_size
    if size == 0:
        raise StatfitError(f"{path} is empty")
    if size > MAX_FILE_BYTES:
        raise StatfitError(f"{path} is {size / 2**30:.1f} GiB; statfit reads splat files up to "
                           f"{MAX_FILE_BYTES / 2**30:.0f} GiB")
    try:
        with path.open("rb") as handle:
            count, mesh_faces, start = _parse_header(handle.read(HEADER_BYTES), path)
            if count * RECORD.itemsize != size - start:
                raise StatfitError(f"{path} declares {count:,} splats ({count * RECORD.itemsize:,} bytes) but holds "
                                   f"{size - start:,} bytes after its header: truncated or damaged")
            if mesh_faces != faces:
                raise StatfitError(f"{path.name} was made for a mesh with {mesh_faces:,} faces; this mesh has "
                                   f"{faces:,}")
            handle.seek(start)
            data = handle.read(count * RECORD.itemsize)
    except OSError as exc:
        raise StatfitError(f"cannot read {path}: {exc.strerror}") from None
    if len(data) != count * RECORD.itemsize:
        raise StatfitError(f"{path} changed while it was read")
    records = np.frombuffer(data, dtype=RECORD)
    _check_values(records, faces, path)
    return records


def _parse_header(head: bytes, path: Path) -> tuple[int, int, int]:
    """Splat count, mesh face count and data offset from the first bytes ``head`` of the file;
    anything but the header :func:`splats_bytes` writes (other comments aside) is refused."""
    end = head.find(b"\nend_header\n") + 1
    if not head.startswith(b"ply\n") or end == 0:
        raise StatfitError(f"{path} is not a PLY file (no 'ply' line, or no end_header in its first "
                           f"{HEADER_BYTES >> 10} KiB)")
    try:
        lines = head[:end].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise StatfitError(f"{path}: the PLY header is not ASCII text") from None
    comments = [line for line in lines if line.startswith(("comment ", "obj_info "))]
    lines = [line.strip() for line in lines if not line.startswith(("comment ", "obj_info "))]
    if len(lines) < 2 or lines[1] != FORMAT_LINE:
        raise StatfitError(f"{path}: splat files are binary little-endian PLY ({FORMAT_LINE!r})")
    element = re.fullmatch(r"element vertex (\d{1,15})", lines[2] if len(lines) > 2 else "", re.ASCII)
    if element is None or lines[3:] != PROPERTY_LINES:
        raise StatfitError(f"{path} is not a statfit splat file: expected one 'element vertex' with the properties "
                           f"{', '.join(line.removeprefix('property ') for line in PROPERTY_LINES)}")
    tied = [re.fullmatch(COMMENT.format(r"(\d{1,15})"), line, re.ASCII) for line in comments]
    mesh_faces = [int(match.group(1)) for match in tied if match]
    if len(mesh_faces) != 1:
        raise StatfitError(f"{path} does not say which mesh its splats are bound to (one header line "
                           f"{COMMENT.format('F')!r})")
    if int(element.group(1)) == 0:
        raise StatfitError(f"{path} holds no splats")
    return int(element.group(1)), mesh_faces[0], end + len(b"end_header\n")


def _check_values(records: np.ndarray, faces: int, path: Path) -> None:
    """Refuse triangle indices outside [0, ``faces``), non-finite values, colours or opacities outside [0, 1]."""
    triangle = records["triangle"]
    if triangle.min() < 0 or triangle.max() >= faces:
        raise StatfitError(f"{path}: triangle indices must lie in [0, {faces}), got {triangle.min()}..{triangle.max()}")
    for name, kind in PROPERTIES:
        if kind == FLOAT and not np.isfinite(records[name]).all():
            raise StatfitError(f"{path}: {name} has NaN or infinite values")
    for name in COLOURS + ("opacity",):
        if records[name].min() < 0 or records[name].max() > 1:
            raise StatfitError(f"{path}: {name} must lie in [0, 1], got {records[name].min()}..{records[name].max()}")
