"""Meshes and point clouds in and out (trimesh), stdin as ``-`` (atomic writes and output checks:
:mod:`statfit.io.files`)."""
from __future__ import annotations

import io
import sys
from pathlib import Path

import numpy as np
import trimesh

from statfit.errors import StatfitError
from statfit.io.files import POINT_TEXT_SUFFIXES, existing_file, points_format
from statfit.io.point_text import SNIFF_BYTES, point_text_bytes, read_point_text
from statfit.structures.scan import Scan

MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off")
SUFFIXES = MESH_SUFFIXES + POINT_TEXT_SUFFIXES      # and text point clouds (statfit.io.point_text)
# The largest mesh or point-cloud file read, and how much of a file its header may take.
MAX_FILE_BYTES = 4 << 30
HEADER_BYTES = 1 << 16


def _load(source: str | Path):
    """trimesh geometry from a path or ``-`` (PLY on stdin), vertex order kept."""
    try:
        if str(source) == "-":
            data = sys.stdin.buffer.read()
            if not data:
                raise StatfitError("no data on standard input (expected a PLY scan)")
            _check_ply_header(data[:HEADER_BYTES], len(data), "standard input")
            return _counted(trimesh.load(io.BytesIO(data), file_type="ply", process=False), data[:HEADER_BYTES],
                            "standard input")
        path = existing_file(source, "file")
        size = path.stat().st_size
        if size == 0:
            raise StatfitError(f"{path} is empty")
        suffix = path.suffix.lower()
        if suffix not in SUFFIXES:
            raise StatfitError(f"{path}: unsupported format {path.suffix!r}; use one of {', '.join(SUFFIXES)}")
        if size > MAX_FILE_BYTES:
            raise StatfitError(f"{path} is {size / 2**30:.1f} GiB; statfit reads meshes up to "
                               f"{MAX_FILE_BYTES / 2**30:.0f} GiB")
        with open(path, "rb") as handle:
            head = handle.read(max(HEADER_BYTES, SNIFF_BYTES))
        if suffix in POINT_TEXT_SUFFIXES:
            return trimesh.PointCloud(read_point_text(path, head))
        if suffix == ".ply":
            _check_ply_header(head, size, str(path))
        geometry = trimesh.load(path, process=False, maintain_order=True)
        return _counted(geometry, head, str(path)) if suffix == ".ply" else geometry
    except StatfitError:
        raise
    except PermissionError:
        raise StatfitError(f"cannot read {source}: permission denied") from None
    except Exception as exc:  # trimesh raises many kinds on corrupt files
        raise StatfitError(f"cannot read {source}: not a valid mesh or point cloud ({type(exc).__name__}: {exc})") from None


def _ply_vertex_count(head: bytes) -> int | None:
    """The vertex count a PLY header declares (None if the header has none)."""
    text = head.split(b"end_header", 1)[0].decode("ascii", errors="replace")
    for line in text.splitlines():
        words = line.split()
        if len(words) == 3 and words[:2] == ["element", "vertex"] and words[2].isdigit():
            return int(words[2])
    return None


def _check_ply_header(head: bytes, size: int, source: str) -> None:
    """Refuse a PLY declaring more vertices than its bytes could hold (≥ 3 bytes each as text)."""
    declared = _ply_vertex_count(head)
    if declared is not None and declared * 3 > size:
        raise StatfitError(f"{source} declares {declared:,} vertices in a file of {size:,} bytes: truncated or damaged")


def _counted(geometry, head: bytes, source: str):
    """``geometry`` loaded from a PLY, refused if it holds other than the declared vertex count."""
    declared = _ply_vertex_count(head)
    held = len(getattr(geometry, "vertices", ()))
    if declared is not None and held != declared:
        raise StatfitError(f"{source} declares {declared:,} vertices but holds {held:,}: truncated or damaged")
    return geometry


def read_points(source: str | Path) -> np.ndarray:
    """Points (M, 3) of a point cloud or mesh file (a mesh's vertices are its points)."""
    return _points_of(_load(source), source)


def _points_of(geometry, source: str | Path) -> np.ndarray:
    """The finite vertices (M, 3) of loaded geometry (all parts of a scene)."""
    if isinstance(geometry, trimesh.Scene):
        parts = [g.vertices for g in geometry.geometry.values() if hasattr(g, "vertices")]
        vertices = np.concatenate(parts) if parts else np.zeros((0, 3))
    else:
        vertices = np.asarray(getattr(geometry, "vertices", np.zeros((0, 3))))
    if len(vertices) == 0:
        raise StatfitError(f"{source} contains no points")
    vertices = np.asarray(vertices, dtype=np.float64)
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise StatfitError(f"{source} has NaN or infinite coordinates ({int(bad.sum())} "
                           f"{'point' if bad.sum() == 1 else 'points'})")
    return vertices


def load_scan(source: str | Path, seed: int = 0) -> Scan:
    """A scan file as the fit takes it: a mesh's points drawn by area (deterministic for ``seed``),
    a point cloud's as they are."""
    geometry = _load(source)
    points = _points_of(geometry, source)
    if isinstance(geometry, trimesh.Trimesh) and len(geometry.faces) > 0:
        return Scan.from_mesh(points, np.asarray(geometry.faces, dtype=np.int64), seed)
    return Scan.from_points(points)


def read_mesh(source: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (N, 3) and faces (F, 3) of a triangle mesh file, in file order."""
    geometry = _load(source)
    if not isinstance(geometry, trimesh.Trimesh) or len(geometry.faces) == 0:
        raise StatfitError(f"{source} is not a triangle mesh")
    vertices = np.asarray(geometry.vertices, dtype=np.float64)
    if not np.isfinite(vertices).all():
        raise StatfitError(f"{source} has NaN or infinite coordinates")
    return vertices, np.asarray(geometry.faces, dtype=np.int64)


def mesh_bytes(vertices: np.ndarray, faces: np.ndarray, file_type: str,
               fields: dict[str, np.ndarray] | None = None) -> bytes:
    """The mesh encoded as ``ply`` (binary) or ``obj``, vertex order kept. ``fields``: per-vertex
    values (N,) each, written as extra PLY vertex properties after x y z in their order (bool as
    uchar, other values as float32); OBJ carries none."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    if file_type == "ply":
        for name, values in (fields or {}).items():
            values = np.asarray(values)
            if values.shape != (len(mesh.vertices),):
                raise StatfitError(f"vertex field {name} has shape {values.shape}; the mesh has {len(mesh.vertices)} vertices")
            mesh.vertex_attributes[name] = values.astype(np.uint8 if values.dtype == bool else np.float32)
    data = mesh.export(file_type=file_type, **({"include_normals": False} if file_type == "obj" else {}))
    return data.encode() if isinstance(data, str) else data


def read_vertex_fields(source: str | Path) -> dict[str, np.ndarray]:
    """The extra per-vertex properties of a PLY (beyond x y z), (N,) float64 each, in file order;
    empty for other formats or a PLY with none (e.g. a fit's ``data_distance``, ``observed``,
    ``off_span``, docs/formats.md)."""
    if str(source) != "-" and Path(source).suffix.lower() != ".ply":
        return {}
    raw = getattr(_load(source), "metadata", {}).get("_ply_raw", {}).get("vertex", {}).get("data")
    if raw is None or raw.dtype.names is None:
        return {}
    return {name: np.asarray(raw[name], dtype=np.float64).reshape(-1) for name in raw.dtype.names
            if name not in ("x", "y", "z") and raw[name].ndim == 1}


def points_bytes(points: np.ndarray, target: str | Path = "-") -> bytes:
    """A point cloud (M, 3) encoded for the path ``target``: binary PLY, or text rows for a text
    point cloud's suffix (:func:`statfit.io.files.points_format`); either way the points as float32,
    so that both files read back to the same points."""
    if points_format(target) == "text":
        return point_text_bytes(np.asarray(points, dtype=np.float32), Path(str(target)).suffix.lower())
    return trimesh.PointCloud(points).export(file_type="ply")
