"""Meshes and point clouds in and out (trimesh), with atomic writes and stdin/stdout as ``-``."""
from __future__ import annotations

import io
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import trimesh

from statfit.errors import StatfitError

MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off")


def _load(source: str | Path):
    """trimesh geometry from a path or ``-`` (PLY on stdin), vertex order kept."""
    try:
        if str(source) == "-":
            data = sys.stdin.buffer.read()
            if not data:
                raise StatfitError("no data on standard input (expected a PLY scan)")
            return trimesh.load(io.BytesIO(data), file_type="ply", process=False)
        path = Path(source)
        if not path.exists():
            raise StatfitError(f"file not found: {path}")
        if not path.is_file():
            raise StatfitError(f"not a file: {path}")
        if path.stat().st_size == 0:
            raise StatfitError(f"{path} is empty")
        if path.suffix.lower() not in MESH_SUFFIXES:
            raise StatfitError(f"{path}: unsupported format {path.suffix!r}; use one of {', '.join(MESH_SUFFIXES)}")
        return trimesh.load(path, process=False, maintain_order=True)
    except StatfitError:
        raise
    except PermissionError:
        raise StatfitError(f"cannot read {source}: permission denied") from None
    except Exception as exc:  # trimesh raises many kinds on corrupt files
        raise StatfitError(f"cannot read {source}: not a valid mesh or point cloud ({type(exc).__name__}: {exc})") from None


def read_points(source: str | Path) -> np.ndarray:
    """Points (M, 3) of a point cloud or mesh file (a mesh's vertices are its points)."""
    geometry = _load(source)
    if isinstance(geometry, trimesh.Scene):
        parts = [g.vertices for g in geometry.geometry.values() if hasattr(g, "vertices")]
        vertices = np.concatenate(parts) if parts else np.zeros((0, 3))
    else:
        vertices = np.asarray(getattr(geometry, "vertices", np.zeros((0, 3))))
    if len(vertices) == 0:
        raise StatfitError(f"{source} contains no points")
    return np.asarray(vertices, dtype=np.float64)


def read_mesh(source: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (N, 3) and faces (F, 3) of a triangle mesh file, in file order."""
    geometry = _load(source)
    if not isinstance(geometry, trimesh.Trimesh) or len(geometry.faces) == 0:
        raise StatfitError(f"{source} is not a triangle mesh")
    vertices = np.asarray(geometry.vertices, dtype=np.float64)
    if not np.isfinite(vertices).all():
        raise StatfitError(f"{source} has NaN or infinite coordinates")
    return vertices, np.asarray(geometry.faces, dtype=np.int64)


def mesh_bytes(vertices: np.ndarray, faces: np.ndarray, file_type: str) -> bytes:
    """The mesh encoded as ``ply`` (binary) or ``obj``, vertex order kept."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    data = mesh.export(file_type=file_type, **({"include_normals": False} if file_type == "obj" else {}))
    return data.encode() if isinstance(data, str) else data


def points_bytes(points: np.ndarray) -> bytes:
    """A point cloud encoded as binary PLY."""
    return trimesh.PointCloud(points).export(file_type="ply")


def write_atomic(target: str | Path, data: bytes) -> None:
    """Write ``data`` to ``target`` via a temporary file in the same folder and a rename, so a
    reader never sees a half-written file; ``-`` writes to stdout."""
    if str(target) == "-":
        sys.stdout.buffer.write(data)
        sys.stdout.buffer.flush()
        return
    path = Path(target)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise StatfitError(f"output folder does not exist: {folder}")
    try:
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as exc:
        raise StatfitError(f"cannot write to {folder}: {exc.strerror}") from None
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
        os.replace(tmp, path)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        raise StatfitError(f"cannot write {path}: {exc.strerror}") from None


def mesh_format(target: str | Path) -> str:
    """``obj`` for a .obj path, else ``ply`` (also for stdout)."""
    return "obj" if Path(str(target)).suffix.lower() == ".obj" else "ply"


def check_writable(target: str | Path) -> None:
    """Fail early, before any work, if ``target``'s folder cannot take a new file."""
    if str(target) == "-":
        return
    folder = Path(target).parent if str(Path(target).parent) else Path(".")
    if not folder.is_dir():
        raise StatfitError(f"output folder does not exist: {folder}")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise StatfitError(f"output folder is not writable: {folder}")
    if Path(target).is_dir():
        raise StatfitError(f"output path is a folder: {target}")
