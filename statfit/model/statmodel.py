"""StatModel: a template mesh plus a linear shape space, loaded from the npz contract.

npz keys: ``v_template (N,3)``, ``faces (F,3)``, ``shapedirs (N,3,K)`` (deformation directions
of any scale, not necessarily orthogonal: a shape is ``v_template + shapedirs @ c``, c ~ N(0, I));
optional ``landmarks (L,)`` vertex indices and ``region_<name>`` vertex-index arrays.

The basis used by the filters is derived by SVD: ``shapedirs`` flattened to (3N, K) equals
``U diag(std) Vᵀ``; ``U`` (3N, K) is orthonormal and ``std`` are the principal standard deviations.
"""
from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from statfit.errors import StatfitError
from statfit.structures.frame import Frame, surface_vertices
from statfit.io.files import write_atomic
from statfit.io.npz import npz_bytes, read_npz
from statfit.structures.kdtree import kd_tree


@dataclass(frozen=True)
class StatModel:
    """A template mesh with an orthonormal PCA basis.

    template: (N, 3) float64 mean shape; faces: (F, 3) int64;
    basis: (3N, K) float64 orthonormal columns, vertex-major flattening (x0, y0, z0, x1, ...);
    std: (K,) float64 principal standard deviations, decreasing.
    """

    template: np.ndarray
    faces: np.ndarray
    basis: np.ndarray
    std: np.ndarray
    landmarks: np.ndarray | None = None
    regions: dict[str, np.ndarray] = field(default_factory=dict)
    source: str = "<arrays>"

    @property
    def num_vertices(self) -> int:
        return self.template.shape[0]

    @property
    def num_modes(self) -> int:
        return self.basis.shape[1]

    @property
    def surface_template(self) -> np.ndarray:
        """(S, 3) the template's vertices that some face uses (all N for most models): what sizes,
        centres and units are measured on (:func:`statfit.structures.frame.surface_vertices`)."""
        return surface_vertices(self.template, self.faces)

    @property
    def frame(self) -> Frame:
        """The template's unit frame (its surface centred, unit RMS radius): the frame fits run in."""
        return Frame.of(self.template, self.faces)

    def truncated(self, k: int) -> "StatModel":
        """The model with only its first ``k`` modes."""
        if not 1 <= k <= self.num_modes:
            raise StatfitError(f"--k must be between 1 and {self.num_modes}, got {k}")
        return StatModel(self.template, self.faces, self.basis[:, :k], self.std[:k],
                         self.landmarks, self.regions, self.source)

    def shape(self, coeffs: np.ndarray) -> np.ndarray:
        """Vertices (N, 3) for coefficients in standard-deviation units, (K,)."""
        coeffs = np.asarray(coeffs, dtype=np.float64)
        return self.template + (self.basis @ (self.std * coeffs)).reshape(-1, 3)

    def sample(self, rng: np.random.Generator, sigma: float = 1.0) -> np.ndarray:
        """A random shape (N, 3) with coefficients ~ N(0, sigma²)."""
        return self.shape(sigma * rng.standard_normal(self.num_modes))

    def variance_explained(self) -> np.ndarray:
        """Cumulative fraction of the model's variance explained by the first k modes, (K,)."""
        var = self.std**2
        return np.cumsum(var) / var.sum()


# A mode moving the template's vertices (RMS) by more than this many of its RMS radii per standard
# deviation describes no population of shapes (the embedded head's first mode: 0.05).
IMPLAUSIBLE_MODE = 1e3


def model_from_arrays(v_template: np.ndarray, faces: np.ndarray, shapedirs: np.ndarray,
                      landmarks: np.ndarray | None = None,
                      regions: dict[str, np.ndarray] | None = None,
                      source: str = "<arrays>") -> StatModel:
    """Validate raw arrays and derive the orthonormal basis (SVD of the flattened shapedirs)."""
    v_template = _float_array(v_template, "v_template")
    faces = np.asarray(faces)
    shapedirs = _float_array(shapedirs, "shapedirs")
    if v_template.ndim != 2 or v_template.shape[1] != 3 or v_template.shape[0] < 3:
        raise StatfitError(f"{source}: v_template must have shape (N, 3), got {v_template.shape}")
    n = v_template.shape[0]
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
        raise StatfitError(f"{source}: faces must have shape (F, 3), got {faces.shape}")
    if not np.issubdtype(faces.dtype, np.integer):
        raise StatfitError(f"{source}: faces must be integers, got {faces.dtype}")
    if faces.min() < 0 or faces.max() >= n:
        raise StatfitError(f"{source}: face indices must lie in [0, {n}), got [{faces.min()}, {faces.max()}]")
    if shapedirs.ndim != 3 or shapedirs.shape[:2] != (n, 3) or shapedirs.shape[2] == 0:
        raise StatfitError(f"{source}: shapedirs must have shape ({n}, 3, K), got {shapedirs.shape}")
    flat = shapedirs.reshape(3 * n, -1)
    u, s, _ = np.linalg.svd(flat, full_matrices=False)
    keep = s > s[0] * 1e-10
    if not keep.any():
        raise StatfitError(f"{source}: shapedirs are all zero")
    scale = Frame.of(v_template, faces).scale
    if scale <= 1e-12 * max(1.0, float(np.abs(v_template).max())):
        raise StatfitError(f"{source}: the template's surface vertices all coincide (RMS radius {scale:.3g}): a mesh "
                           "without extent")
    if (move := float(s[0]) / np.sqrt(n)) > IMPLAUSIBLE_MODE * scale:      # the vertices' RMS move
        raise StatfitError(f"{source}: the first mode moves the template's vertices by {move / scale:.3g} of its RMS "
                           "radius per standard deviation: shapedirs are per standard deviation (people differ by a "
                           "fraction of it)")
    regions = {k: _index_array(v, n, f"{source}: region_{k}") for k, v in (regions or {}).items()}
    if landmarks is not None:
        landmarks = _index_array(landmarks, n, f"{source}: landmarks")
    return StatModel(v_template, faces.astype(np.int64), u[:, keep], s[keep], landmarks, regions, source)


def load_model(path: str | Path, k: int | None = None) -> StatModel:
    """Load and validate a model npz; keep the first ``k`` modes when given."""
    path = Path(path)
    arrays = read_npz(path)
    refuse_texture_model(arrays, path)
    missing = [key for key in ("v_template", "faces", "shapedirs") if key not in arrays]
    if missing:
        raise StatfitError(f"model {path} lacks the key(s) {', '.join(missing)}")
    regions = {key[len("region_"):]: arr for key, arr in arrays.items() if key.startswith("region_")}
    model = model_from_arrays(arrays["v_template"], arrays["faces"], arrays["shapedirs"],
                              arrays.get("landmarks"), regions, source=str(path))
    return model.truncated(k) if k is not None else model


def refuse_texture_model(arrays: dict[str, np.ndarray], path: str | Path) -> None:
    """Raise a clear error when the npz ``arrays`` hold a texture model (``kind = "texture"``)."""
    if np.asarray(arrays.get("kind", "")).reshape(-1).tolist() == ["texture"]:
        raise StatfitError(f"{path} is a texture model (for `statfit inpaint --model`), not a mesh model")


def model_arrays(model: StatModel, dtype: type = np.float64) -> dict[str, np.ndarray]:
    """The npz-contract arrays of ``model`` (shapedirs = basis scaled by the std-devs, as ``dtype``)."""
    shapedirs = (model.basis * model.std).reshape(model.num_vertices, 3, model.num_modes).astype(dtype)
    arrays = {"v_template": model.template, "faces": model.faces, "shapedirs": shapedirs}
    if model.landmarks is not None:
        arrays["landmarks"] = model.landmarks
    arrays.update({f"region_{name}": index for name, index in model.regions.items()})
    return arrays


def save_model(model: StatModel, path: str | Path, dtype: type = np.float64) -> None:
    """Write ``model`` as an npz in the contract, atomically, with reproducible bytes; ``dtype``
    the shapedirs' (float32 halves a large model)."""
    write_atomic(path, npz_bytes(model_arrays(model, dtype)))


def with_regions(model: StatModel, regions: dict[str, np.ndarray], source: str = "regions") -> StatModel:
    """``model`` with named vertex subsets added (or replaced), validated as vertex indices."""
    for name in regions:
        if not re.fullmatch(r"[A-Za-z0-9_]+", name):
            raise StatfitError(f"{source}: region name {name!r} must be letters, digits and underscores")
    checked = {name: _index_array(index, model.num_vertices, f"{source}: {name}") for name, index in regions.items()}
    return dataclasses.replace(model, regions={**model.regions, **checked})


def with_landmarks(model: StatModel, indices: np.ndarray, source: str = "landmarks") -> StatModel:
    """``model`` with its landmark vertex indices (L,) set, validated."""
    return dataclasses.replace(model, landmarks=_index_array(indices, model.num_vertices, source))


def region_vertices(model: StatModel, name: str) -> np.ndarray:
    """The vertex indices of the region ``name``; a clear error lists the model's regions, or says it is empty."""
    if name not in model.regions:
        known = ", ".join(sorted(model.regions)) or "none"
        raise StatfitError(f"the model has no region {name!r} (its regions: {known})")
    if not len(model.regions[name]):
        raise StatfitError(f"the model's region {name!r} holds no vertex ({model.source})")
    return model.regions[name]


def region_triangles(model: StatModel, name: str) -> np.ndarray:
    """(F,) bool: the triangles whose three vertices all lie in the region ``name``."""
    mask = np.isin(model.faces, region_vertices(model, name)).all(axis=1)
    if not mask.any():
        raise StatfitError(f"the model's region {name!r} contains no whole triangle ({model.source})")
    return mask


# With clutter, the data term keeps to the face: its region, or this many RMS radii around the
# landmarks (ICT: 5.7 cm; 0.7 let the hair in: face error 1.48 mm against 0.70 at 0.5 and 1.73 for
# the whole head; docs/method.md, "The registration objective").
FACE_RADIUS = 0.5


def face_triangles(model: StatModel, radius: float = FACE_RADIUS) -> np.ndarray | None:
    """(F,) bool: the model's face — its ``face`` region, else the vertices within ``radius`` RMS
    radii of a landmark — or None for a model with neither."""
    if model.regions and "face" in model.regions:
        return region_triangles(model, "face")
    if model.landmarks is None:
        return None
    nearest, _ = kd_tree(model.template[model.landmarks]).query(model.template)
    inside = nearest < radius * model.frame.scale
    return inside[model.faces].all(axis=1)


# Where hair can lie, in RMS radii of the template (ICT: 1.4 and 2.9 cm): above the face's highest
# point by SCALP_ABOVE, or behind its deepest by SCALP_BEHIND (down to its middle height). Hair over
# the scalp is what tilts a cluttered scan's pose and pulls its fit (docs/studies.md §16, "The scalp
# as a region": face error with clutter +1.0% over clean; 0.0 / 0.3 above +2.9% / +6.2%, 0.8 behind
# +19.9%, no region +27.5%).
SCALP_ABOVE = 0.15
SCALP_BEHIND = 0.3


def scalp_triangles(model: StatModel) -> np.ndarray | None:
    """(F,) bool: the triangles hair can cover — a vertex SCALP_ABOVE radii above the face's
    highest point, or SCALP_BEHIND behind its deepest and above its middle height (the model's +y
    up, +z its face's direction, as FLAME, ICT, BFM and the embedded model are built). The face is
    the model's ``face`` region, else its landmarks (which must then be the face's: a landmark on
    the crown or an ear would move the scalp); None for a model with neither."""
    if model.regions and "face" in model.regions:
        anchors = model.template[region_vertices(model, "face")]
    elif model.landmarks is not None:
        anchors = model.template[model.landmarks]
    else:
        return None
    frame = model.frame
    up, forward = model.template[:, 1], model.template[:, 2]
    above = up > anchors[:, 1].max() + SCALP_ABOVE * frame.scale
    behind = (forward < anchors[:, 2].min() - SCALP_BEHIND * frame.scale) & (up > anchors[:, 1].mean())
    return (above | behind)[model.faces].any(axis=1)


# Largest bounding-box side of a head (0.1–0.5 m) or a body (1–2.5 m) in each unit.
_UNIT_RANGES = (("metres (head-sized)", 0.1, 0.5), ("metres (body-sized)", 1.0, 2.5),
                ("centimetres (head-sized)", 10.0, 50.0), ("millimetres (head-sized)", 100.0, 500.0))


def units_guess(template: np.ndarray) -> str:
    """A guess of the model's length unit from its largest extent, or ``unknown``."""
    extent = float(np.ptp(template, axis=0).max())
    return next((name for name, low, high in _UNIT_RANGES if low <= extent <= high), "unknown")


def default_model_path() -> Path:
    """Path of the embedded synthetic default model."""
    from statfit_data import default_model_path as path

    return path()


def _float_array(arr: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(arr)
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise StatfitError(f"{name} must be real numbers, got {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise StatfitError(f"{name} contains NaN or infinite values")
    return arr


def _index_array(arr: np.ndarray, n: int, name: str) -> np.ndarray:
    arr = np.asarray(arr).reshape(-1)
    if not np.issubdtype(arr.dtype, np.integer) or (arr.size and (arr.min() < 0 or arr.max() >= n)):
        raise StatfitError(f"{name} must be vertex indices in [0, {n})")
    return arr.astype(np.int64)
