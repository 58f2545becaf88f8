"""Basel Face Model 2017 (statismo HDF5): ``shape/model/{mean, pcaBasis, pcaVariance}`` and
``shape/representer/cells``.

``mean`` (3N,) is vertex-major (x0, y0, z0, x1, ...); ``pcaBasis`` (3N, K) has orthonormal columns and
``pcaVariance`` (K,) their variances, so the contract's directions are ``pcaBasis · sqrt(pcaVariance)``.
``cells`` is (3, F). The optional ``expression`` group (model2017-1_face12) has the same layout and
the same points. Units are the file's (millimetres for BFM 2017).
"""
from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from statfit.errors import StatfitError
from statfit.io.npz import MAX_BYTES
from statfit.model.statmodel import StatModel, model_from_arrays

HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _dataset(handle, key: str, path: Path) -> np.ndarray:
    dataset = handle.get(key)
    if not isinstance(dataset, h5py.Dataset):
        raise StatfitError(f"{path}: not a Basel Face Model file (no {key} dataset in the HDF5 file)")
    if dataset.size * dataset.dtype.itemsize > MAX_BYTES:  # from the metadata, before reading
        raise StatfitError(f"{path}: {key} declares {dataset.shape}, more than the {MAX_BYTES / 2**30:.0f} GiB "
                           "statfit reads")
    return np.asarray(dataset[()])


def _directions(handle, group: str, n: int, k: int | None, path: Path) -> np.ndarray:
    """(N, 3, K) scaled directions of ``group`` (shape or expression)."""
    basis = _dataset(handle, f"{group}/model/pcaBasis", path)
    variance = _dataset(handle, f"{group}/model/pcaVariance", path).reshape(-1)
    if basis.ndim != 2 or basis.shape != (3 * n, variance.size):
        raise StatfitError(f"{path}: {group}/model/pcaBasis has shape {basis.shape}, expected ({3 * n}, {variance.size})")
    if (variance < 0).any():
        raise StatfitError(f"{path}: {group}/model/pcaVariance has negative values")
    if k is not None:
        if not 1 <= k <= variance.size:
            raise StatfitError(f"--k must be between 1 and {variance.size}, the model's {group} directions")
        basis, variance = basis[:, :k], variance[:k]
    return (basis * np.sqrt(variance)).reshape(n, 3, -1)


def import_bfm(path: str | Path, *, k: int | None = None, expressions: bool = False) -> StatModel:
    """A StatModel from a BFM 2017 h5 file: the shape directions (first ``k``), plus the expression
    directions with ``expressions``."""
    path = Path(path)
    try:
        handle = h5py.File(path, "r")
    except OSError as exc:
        raise StatfitError(f"cannot read {path}: not a valid HDF5 file ({exc})") from None
    with handle:
        mean = _dataset(handle, "shape/model/mean", path).reshape(-1)
        cells = _dataset(handle, "shape/representer/cells", path)
        if mean.size % 3 or cells.ndim != 2 or 3 not in cells.shape:
            raise StatfitError(f"{path}: shape/model/mean {mean.shape} or shape/representer/cells {cells.shape} "
                               "is not a triangle mesh")
        n = mean.size // 3
        directions = _directions(handle, "shape", n, k, path)
        if expressions:
            if "expression" not in handle:
                raise StatfitError(f"{path}: the model has no expression directions")
            directions = np.concatenate([directions, _directions(handle, "expression", n, None, path)], axis=2)
    faces = cells.T if cells.shape[0] == 3 else cells
    return model_from_arrays(mean.reshape(n, 3), faces.astype(np.int64), directions, source=f"{path} (BFM)")
