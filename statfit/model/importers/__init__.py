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
        return load_model(path, k)
    if kind == "ict":
        return import_ict(path, k=k, region=region)
    if kind == "bfm":
        return import_bfm(path, k=k, expressions=expressions)
    arrays = smpl.read_pickle(path) if kind == "smpl-pickle" else _read_npz(path, smpl.REQUIRED_KEYS + smpl.SMPLX_KEYS)[1]
    return smpl.from_arrays(arrays, str(path), k=k, expressions=expressions)


def _read_npz(path: Path, keys: tuple[str, ...] = ()) -> tuple[set[str], dict[str, np.ndarray]]:
    """An npz's key names and its arrays ``keys`` (other members, e.g. the pickled dicts in SMPL-X
    files, are never unpickled)."""
    try:
        check_npz_sizes(path, "model")
        with np.load(path, allow_pickle=False) as data:
            return set(data.files), {key: data[key] for key in keys if key in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise StatfitError(f"cannot read {path}: {exc}") from None
