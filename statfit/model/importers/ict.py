"""ICT-FaceKit (FaceXModel folder): ``generic_neutral_mesh.obj`` plus ``identityNNN.obj`` meshes.

Every OBJ shares the neutral's vertex order; the identity directions are ``identity_i − neutral``
(scaled for coefficients ~ N(0, 1)). The full mesh holds several geometries in fixed vertex ranges
(``REGIONS``, from the ICT-FaceKit README); ``face+head`` keeps the face and the head-and-neck skin.
Quads are split into two triangles with the same winding. Units are the file's (centimetres).
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from statfit.errors import StatfitError
from statfit.model.statmodel import StatModel, model_from_arrays

NEUTRAL = "generic_neutral_mesh.obj"
IDENTITY_PATTERN = re.compile(r"identity(\d+)\.obj$")
DEFAULT_REGION = "face+head"
# Vertex index ranges [start, stop) of the ICT-FaceKit geometries (README "Face Model Topology").
REGIONS: dict[str, tuple[int, int]] = {
    "face": (0, 9409),
    "head": (9409, 11248),
    "mouth_socket": (11248, 13294),
    "eye_socket_left": (13294, 13678),
    "eye_socket_right": (13678, 14062),
    "gums_tongue": (14062, 17039),
    "teeth": (17039, 21451),
    "eyeball_left": (21451, 23021),
    "eyeball_right": (23021, 24591),
}


def read_obj(path: Path, with_faces: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Vertices (N, 3) in file order and, with ``with_faces``, triangles (F, 3): polygons are split
    into fans (a quad a b c d → a b c, a c d). Texture and normal indices are ignored, so vertices
    are never duplicated or merged."""
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise StatfitError(f"cannot read {path}: {exc.strerror}") from None
    try:
        vertices = np.array([line.split()[1:4] for line in lines if line.startswith("v ")], dtype=np.float64)
    except ValueError:  # ragged rows or text
        raise StatfitError(f"{path}: a vertex line is not three numbers") from None
    if not vertices.size:
        raise StatfitError(f"{path} has no vertices")
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise StatfitError(f"{path}: a vertex line is not three numbers")
    if not with_faces:
        return vertices, None
    try:
        polygons = [[int(token.split("/")[0]) for token in line.split()[1:]] for line in lines if line.startswith("f ")]
    except ValueError:
        raise StatfitError(f"{path}: a face line has an index that is not an integer") from None
    triangles = []
    for size in sorted({len(p) for p in polygons}):
        if size < 3:
            raise StatfitError(f"{path} has a face with {size} vertices")
        group = np.array([p for p in polygons if len(p) == size], dtype=np.int64)
        group = np.where(group < 0, group + len(vertices), group - 1)  # OBJ: 1-based, negative = from the end
        fan = np.arange(1, size - 1)
        triangles.append(np.stack([np.repeat(group[:, :1], fan.size, axis=1), group[:, fan], group[:, fan + 1]],
                                  axis=2).reshape(-1, 3))
    if not triangles:
        raise StatfitError(f"{path} has no faces")
    faces = np.concatenate(triangles)
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise StatfitError(f"{path}: a face refers to a vertex that does not exist ({len(vertices)} vertices)")
    return vertices, faces


def identity_files(folder: Path) -> list[Path]:
    """The folder's ``identityNNN.obj`` files in numeric order."""
    files = [p for p in folder.iterdir() if IDENTITY_PATTERN.fullmatch(p.name)]
    return sorted(files, key=lambda p: int(IDENTITY_PATTERN.fullmatch(p.name).group(1)))


def select_regions(spec: str, num_vertices: int, table: dict[str, tuple[int, int]]
                   ) -> dict[str, np.ndarray]:
    """Vertex indices of each region named in ``spec`` (``face+head``), checked against the table
    and the mesh's vertex count."""
    names = [name for name in spec.split("+") if name]
    unknown = [name for name in names if name not in table]
    if unknown or not names:
        raise StatfitError(f"unknown ICT region {'+'.join(unknown) or spec!r}; choose from {', '.join(table)} "
                           "joined by '+'")
    for name in names:
        if table[name][1] > num_vertices:
            raise StatfitError(f"the ICT region {name} needs vertices up to {table[name][1]}, "
                               f"but the mesh has {num_vertices}")
    return {name: np.arange(*table[name]) for name in names}


def import_ict(folder: str | Path, *, k: int | None = None, region: str | None = None) -> StatModel:
    """A StatModel from an ICT-FaceKit folder, cut to ``region`` (default ``face+head``); the
    output keeps each named region as ``region_<name>``."""
    folder = Path(folder)
    neutral, faces = read_obj(folder / NEUTRAL)
    files = identity_files(folder)
    if not files:
        raise StatfitError(f"{folder} has {NEUTRAL} but no identityNNN.obj files")
    if k is not None:
        if not 1 <= k <= len(files):
            raise StatfitError(f"--k must be between 1 and {len(files)}, the folder's identity meshes")
        files = files[:k]
    regions = select_regions(region or DEFAULT_REGION, len(neutral), REGIONS)
    keep = np.unique(np.concatenate(list(regions.values())))
    directions = np.empty((len(keep), 3, len(files)))
    for i, file in enumerate(files):
        vertices, _ = read_obj(file, with_faces=False)
        if len(vertices) != len(neutral):
            raise StatfitError(f"{file} has {len(vertices)} vertices, the neutral mesh {len(neutral)}")
        directions[:, :, i] = vertices[keep] - neutral[keep]
    new_index = np.full(len(neutral), -1)
    new_index[keep] = np.arange(len(keep))
    inside = faces[(new_index[faces] >= 0).all(axis=1)]
    return model_from_arrays(neutral[keep], new_index[inside], directions,
                             regions={name: new_index[index] for name, index in regions.items()},
                             source=f"{folder} (ICT-FaceKit)")
