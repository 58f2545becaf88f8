"""Read the statistical models people already have (FLAME, SMPL-X, SMPL, ICT-FaceKit, Basel 2017)
into a StatModel; ``import_model`` detects the format from the path's kind and content."""
from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from statfit.errors import StatfitError
from statfit.io.files import existing_file
from statfit.io.npz import check_npz_sizes
from statfit.model.importers import smpl
from statfit.model.importers.bfm import HDF5_SIGNATURE, import_bfm
from statfit.model.importers.ict import NEUTRAL, import_ict
from statfit.model.importers.masks import read_masks
from statfit.io.landmarks import read_landmark_indices
from statfit.model.statmodel import StatModel, load_model, refuse_texture_model, with_landmarks, with_regions

CONTRACT_KEYS = ("v_template", "faces", "shapedirs")
# What a statfit npz holds besides: read by every command (``load_model``).
OPTIONAL_KEYS = ("landmarks", "kind")
# The light ICT-FaceKit npz (../shared/data/ict-face, its README): its 68 Multi-PIE landmark vertices and
# the face geometry's vertex count (vertices [0, count)). Every command's ``--model`` reads them as the
# contract's ``landmarks`` and ``region_face_geometry`` (:func:`with_light_keys`), and ``model import``
# stores them so; the contract's own reader (``load_model``) leaves them out, as any key it does not read.
# Not as ``region_face``: the hair rules of a cluttered scan take a ``face`` region as the face
# (statfit.model.statmodel.face_triangles), and ICT's face geometry reaches over the forehead to the
# scalp and ears — the face error of cluttered ICT scans was 0.96 mm with it as ``face`` against 0.39 mm
# with the landmarks alone (4 people, 50% clutter; studies/face_region_clutter.py).
LIGHT_LANDMARKS, LIGHT_FACE_COUNT, LIGHT_FACE_REGION = "landmarks68", "face_vertex_count", "face_geometry"
FORMATS = "a statfit model npz, a FLAME/SMPL-X/SMPL pickle or npz, an ICT-FaceKit folder or a BFM 2017 h5 file"


def model_format(path: str | Path) -> str:
    """``statfit`` (an npz in the contract), ``smpl-npz``, ``smpl-pickle``, ``ict`` or ``bfm``."""
    path = Path(path)
    if path.is_dir():
        if (path / NEUTRAL).is_file():
            return "ict"
        raise StatfitError(f"{path} is a folder without {NEUTRAL}: not an ICT-FaceKit model")
    existing_file(path, "model file")
    with path.open("rb") as handle:
        head = handle.read(8)
    if not head:
        raise StatfitError(f"{path} is empty")
    if head == HDF5_SIGNATURE:
        return "bfm"
    if zipfile.is_zipfile(path):
        keys, arrays = _read_npz(path, ("kind",))
        refuse_texture_model(arrays, path)
        if all(key in keys for key in CONTRACT_KEYS):
            return "statfit"
        if all(key in keys for key in smpl.REQUIRED_KEYS):
            return "smpl-npz"
        raise StatfitError(f"{path} is an npz without a model's keys (found {', '.join(sorted(keys)) or 'none'}; "
                           f"expected {', '.join(CONTRACT_KEYS)} or {', '.join(smpl.REQUIRED_KEYS)})")
    if head[:1] == b"\x80" or path.suffix.lower() in (".pkl", ".pickle"):
        return "smpl-pickle"
    raise StatfitError(f"{path}: unknown model format; expected {FORMATS}")


def import_model(path: str | Path, *, k: int | None = None, expressions: bool = False,
                 region: str | None = None, masks: str | Path | None = None,
                 landmarks: str | Path | None = None) -> StatModel:
    """The model at ``path`` in any supported format: the first ``k`` identity directions (all by
    default), the expression directions too with ``expressions`` (FLAME, SMPL-X, BFM), for an
    ICT-FaceKit folder the geometries named in ``region`` (default ``face+head``), the named vertex
    subsets of a ``masks`` file (e.g. FLAME_masks.pkl) as regions, and the vertex indices of a
    ``landmarks`` text file as the model's landmarks."""
    model = _import(path, k=k, expressions=expressions, region=region)
    if masks is not None:
        model = with_regions(model, read_masks(masks), str(masks))
    if landmarks is not None:
        model = with_landmarks(model, read_landmark_indices(landmarks), f"{landmarks}: landmark indices")
    return model


def _import(path: str | Path, *, k: int | None, expressions: bool, region: str | None) -> StatModel:
    kind = model_format(path)
    if region is not None and kind != "ict":
        raise StatfitError("--region on import cuts an ICT-FaceKit folder; fitting commands take --region "
                           "to fit a stored region")
    if expressions and kind in ("statfit", "ict"):
        raise StatfitError(f"{path}: --expressions applies to FLAME, SMPL-X and BFM models")
    if kind == "statfit":
        return with_light_keys(load_model(path, k), Path(path))
    if kind == "ict":
        return import_ict(path, k=k, region=region)
    if kind == "bfm":
        return import_bfm(path, k=k, expressions=expressions)
    arrays = smpl.read_pickle(path) if kind == "smpl-pickle" else _read_npz(path, smpl.REQUIRED_KEYS + smpl.SMPLX_KEYS)[1]
    return smpl.from_arrays(arrays, str(path), k=k, expressions=expressions)


def unread_npz_keys(path: str | Path) -> list[str]:
    """The keys of a statfit npz that no command reads (sorted; [] for other formats), e.g. an
    exporter's own names for landmarks or regions."""
    path = Path(path)
    if model_format(path) != "statfit":
        return []
    keys, _ = _read_npz(path)
    read = CONTRACT_KEYS + OPTIONAL_KEYS + (LIGHT_LANDMARKS, LIGHT_FACE_COUNT)
    return sorted(key for key in keys if key not in read and not key.startswith("region_"))


def with_light_keys(model: StatModel, path: Path) -> StatModel:
    """``model`` with the light ICT-FaceKit npz's landmarks and face geometry (as the region
    ``face_geometry``), where it has them and not the contract's own."""
    _, arrays = _read_npz(path, (LIGHT_LANDMARKS, LIGHT_FACE_COUNT))
    if LIGHT_LANDMARKS in arrays and model.landmarks is None:
        model = with_landmarks(model, arrays[LIGHT_LANDMARKS], f"{path}: {LIGHT_LANDMARKS}")
    if LIGHT_FACE_COUNT in arrays and LIGHT_FACE_REGION not in model.regions:
        count = np.asarray(arrays[LIGHT_FACE_COUNT])
        if count.shape != () or not np.issubdtype(count.dtype, np.integer) or not 0 < int(count) <= model.num_vertices:
            raise StatfitError(f"{path}: {LIGHT_FACE_COUNT} must be one whole number in 1..{model.num_vertices}")
        model = with_regions(model, {LIGHT_FACE_REGION: np.arange(int(count))}, f"{path}: {LIGHT_FACE_COUNT}")
    return model


def _read_npz(path: Path, keys: tuple[str, ...] = ()) -> tuple[set[str], dict[str, np.ndarray]]:
    """An npz's key names and its arrays ``keys`` (other members, e.g. the pickled dicts in SMPL-X
    files, are never unpickled)."""
    try:
        check_npz_sizes(path, "model")
        with np.load(path, allow_pickle=False) as data:
            return set(data.files), {key: data[key] for key in keys if key in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise StatfitError(f"cannot read {path}: {exc}") from None
