"""Read the MakeHuman base mesh and its morph targets (the CC0 ``makehuman`` folder layout:
``3dobjs/base.obj.gz``, ``targets/<category>/**/*.target.gz``, ``targets/target.json``,
``mesh_metadata/basemesh_vertex_groups.json``) as arrays in metres, restricted to the skin
(the ``body`` vertex group): what :mod:`statfit.model.importers.makehuman_shapes` turns into bodies.

Every file is gzip or JSON read with a cap on its decompressed size, so a decompression bomb is
refused after reading at most the cap."""
from __future__ import annotations

import gzip
import io
import json
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from statfit.errors import StatfitError
from statfit.io.makehuman_layout import BASE_MESH, SLIDERS, TARGETS, VERTEX_GROUPS, makehuman_folder

DECIMETRE = 0.1  # MakeHuman's unit, in metres
BODY_GROUP = "body"
MAX_FILE_BYTES = 64 << 20  # decompressed; the base mesh is ~2 MB, the largest target ~1 MB


@dataclass(frozen=True)
class Target:
    """A sparse morph target: body vertex indices (M,) and their displacements (M, 3) in metres."""

    indices: np.ndarray
    deltas: np.ndarray


@dataclass(frozen=True)
class MakeHumanData:
    """The skin of the base mesh and every target that moves it.

    vertices: (N, 3) metres, file order; faces: (F, 3) triangles (each quad split in two);
    targets: name (path below ``targets/`` without ``.target.gz``, e.g. ``arms/l-hand-scale-incr``)
    → :class:`Target`; sliders: ``target.json`` as read; groups: vertex-group name → body vertex
    indices (e.g. ``Left``, ``Right``)."""

    vertices: np.ndarray
    faces: np.ndarray
    targets: dict[str, Target]
    sliders: dict
    groups: dict[str, np.ndarray]


def read_makehuman(folder: str | Path, progress: Callable[[int, int], None] | None = None) -> MakeHumanData:
    """Read a MakeHuman folder; a folder of another layout is refused with one line naming what is missing.
    ``progress(done, total)`` is called after each morph target read (1,258 of them: ~5 s on one core)."""
    folder = makehuman_folder(folder)
    groups = _vertex_groups(folder / VERTEX_GROUPS)
    if BODY_GROUP not in groups:
        raise StatfitError(f"{folder / VERTEX_GROUPS} has no {BODY_GROUP!r} group")
    body = groups[BODY_GROUP]
    count = int(body.max()) + 1
    if not np.array_equal(body, np.arange(count)):
        raise StatfitError(f"{folder / VERTEX_GROUPS}: the {BODY_GROUP!r} group must be the first vertices, in order")
    vertices, faces = _body_mesh(folder / BASE_MESH, count)
    targets = {}
    paths = sorted((folder / TARGETS).rglob("*.target.gz"))
    for done, path in enumerate(paths, 1):
        name = path.relative_to(folder / TARGETS).as_posix().removesuffix(".target.gz")
        target = _target(path, count)
        if target.indices.size:
            targets[name] = target
        if progress is not None:
            progress(done, len(paths))
    if not targets:
        raise StatfitError(f"{folder / TARGETS} holds no morph target (*.target.gz)")
    sliders = _json(folder / SLIDERS)
    kept = {name: idx[idx < count] for name, idx in groups.items()}
    return MakeHumanData(vertices, faces, targets, sliders, {k: v for k, v in kept.items() if v.size})


def _read_capped(path: Path) -> bytes:
    """The (decompressed, for ``.gz``) bytes of ``path``; refuses more than ``MAX_FILE_BYTES``."""
    try:
        with (gzip.open(path, "rb") if path.suffix == ".gz" else path.open("rb")) as handle:
            data = handle.read(MAX_FILE_BYTES + 1)
    except (OSError, EOFError, zlib.error) as exc:
        raise StatfitError(f"cannot read {path}: {exc}") from None
    if len(data) > MAX_FILE_BYTES:
        raise StatfitError(f"{path} decompresses to more than {MAX_FILE_BYTES >> 20} MiB; refusing it")
    return data


def _json(path: Path):
    try:
        return json.loads(_read_capped(path))
    except (ValueError, UnicodeDecodeError) as exc:
        raise StatfitError(f"cannot read {path}: not JSON ({exc})") from None


def _vertex_groups(path: Path) -> dict[str, np.ndarray]:
    """Group name → sorted vertex indices, from ``{name: [[first, last], ...]}`` inclusive ranges."""
    groups = {}
    for name, ranges in _json(path).items():
        try:
            spans = np.asarray(ranges, dtype=np.int64).reshape(-1, 2)
        except (TypeError, ValueError):
            raise StatfitError(f"{path}: group {name!r} is not a list of [first, last] ranges") from None
        if spans.size and (spans.min() < 0 or (spans[:, 1] < spans[:, 0]).any()):
            raise StatfitError(f"{path}: group {name!r} has an invalid range")
        groups[name] = np.concatenate([np.arange(a, b + 1) for a, b in spans]) if spans.size else spans[:, 0]
    return groups


def _body_mesh(path: Path, count: int) -> tuple[np.ndarray, np.ndarray]:
    """The first ``count`` vertices (metres) and the ``body`` group's faces, quads split into triangles."""
    vertices, faces, group = [], [], None
    for line in _read_capped(path).decode("utf-8", "replace").splitlines():
        if line.startswith("v "):
            vertices.append(line.split()[1:4])
        elif line.startswith("g "):
            group = line.split()[1] if len(line.split()) > 1 else None
        elif line.startswith("f ") and group == BODY_GROUP:
            faces.append([int(corner.split("/")[0]) - 1 for corner in line.split()[1:]])
    try:
        vertices = np.array(vertices, dtype=np.float64)
    except ValueError:
        raise StatfitError(f"{path}: a vertex line is not three numbers") from None
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < count:
        raise StatfitError(f"{path} holds {len(vertices)} vertices; the {BODY_GROUP!r} group needs {count}")
    if not faces or any(len(face) not in (3, 4) for face in faces):
        raise StatfitError(f"{path}: the {BODY_GROUP!r} group must hold triangles or quads")
    quads = np.array([face if len(face) == 4 else face + [face[2]] for face in faces], dtype=np.int64)
    if quads.min() < 0 or quads.max() >= count:
        raise StatfitError(f"{path}: a {BODY_GROUP!r} face uses a vertex outside the group")
    triangles = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    triangles = triangles[(triangles[:, 1] != triangles[:, 2])]  # a triangle given as a quad adds nothing
    return vertices[:count] * DECIMETRE, triangles


def _target(path: Path, count: int) -> Target:
    """A ``vertex dx dy dz`` target (decimetres), kept to the vertices below ``count``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # a target that moves nothing: "input contained no data"
        try:  # numpy's C parser: 1.3–1.5× faster than splitting the text in Python (the 1,258 targets: 5.2 s, 6.9–7.7 before)
            table = np.loadtxt(io.BytesIO(_read_capped(path)), dtype=np.float64, comments="#", ndmin=2)
        except ValueError:
            table = None
    if table is None or (table.size and table.shape[1] != 4):
        raise StatfitError(f"{path}: each line must be 'vertex dx dy dz'")
    table = table.reshape(-1, 4)
    indices = table[:, 0].astype(np.int64)
    if (indices < 0).any() or not np.isfinite(table).all():
        raise StatfitError(f"{path}: negative vertex index or non-finite displacement")
    keep = indices < count
    return Target(indices[keep], table[keep, 1:] * DECIMETRE)
