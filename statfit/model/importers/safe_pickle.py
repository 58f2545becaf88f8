"""Load model pickles (FLAME, SMPL-X: Python-2 era, chumpy arrays, scipy sparse) without running their code.

A pickle names the callables that rebuild its objects; ``pickle.load`` would import and call any of
them (``os.system`` included). This unpickler resolves only a fixed list: numpy array, dtype and scalar
reconstruction, builtin containers, and stand-ins for chumpy's ``Ch`` objects and scipy's sparse
matrices that merely collect their pickled state. Every other name is refused. After loading, the
stand-ins are replaced by numpy arrays (a ``Ch``'s value ``x``) and scipy matrices built from their
index arrays. chumpy itself is not needed.
"""
from __future__ import annotations

import _compat_pickle
import builtins
import codecs
import io
import pickle
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse

from statfit.errors import StatfitError


class _Pickled:
    """A stand-in for a class we do not import: keeps the class name and the pickled state."""

    source = "object"
    state: Any = None  # NEWOBJ creates instances without calling __init__

    def __setstate__(self, state: Any) -> None:
        self.state = state


class _Chumpy(_Pickled):
    pass


class _Sparse(_Pickled):
    pass


def _stand_in(base: type, module: str, name: str) -> type:
    return type(name, (base,), {"source": f"{module}.{name}"})


def _latin1_encode(text: str, encoding: str = "latin1") -> bytes:
    """``_codecs.encode`` as Python 3 pickles bytes with protocol 2, restricted to latin-1."""
    if encoding != "latin1" or not isinstance(text, str):
        raise StatfitError("refusing to load this pickle: unexpected use of _codecs.encode")
    return codecs.encode(text, "latin1")


def _reconstructor(cls: type, base: type, state: Any) -> Any:
    """``copyreg._reconstructor`` (protocol 0/1 objects), only for the stand-in classes."""
    if not (isinstance(cls, type) and issubclass(cls, _Pickled)) or base is not object or state is not None:
        raise StatfitError("refusing to load this pickle: it reconstructs an object of a class not allowed")
    return object.__new__(cls)


try:  # numpy ≥ 2 moved numpy.core to numpy._core; pickles name either
    from numpy._core import multiarray as _multiarray
except ImportError:  # pragma: no cover - numpy 1.x
    from numpy.core import multiarray as _multiarray

_NUMPY_MODULES = ("numpy.core.multiarray", "numpy._core.multiarray")
_ALLOWED: dict[tuple[str, str], Any] = {
    **{(module, name): getattr(_multiarray, name) for module in _NUMPY_MODULES for name in ("_reconstruct", "scalar")},
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
    ("copyreg", "_reconstructor"): _reconstructor,
    ("_codecs", "encode"): _latin1_encode,
    **{("builtins", name): getattr(builtins, name) for name in ("object", "set", "frozenset", "slice", "complex")},
}
_SPARSE_MODULES = ("scipy.sparse.csc", "scipy.sparse.csr", "scipy.sparse.coo",
                   "scipy.sparse._csc", "scipy.sparse._csr", "scipy.sparse._coo")
_SPARSE_CLASSES = ("csc_matrix", "csr_matrix", "coo_matrix", "csc_array", "csr_array", "coo_array")


class _RestrictedUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        # Python-2 names (__builtin__, copy_reg) as pickle's own fix_imports maps them.
        module, name = _compat_pickle.NAME_MAPPING.get((module, name), (module, name))
        module = _compat_pickle.IMPORT_MAPPING.get(module, module)
        if (module, name) in _ALLOWED:
            return _ALLOWED[(module, name)]
        if module == "chumpy" or module.startswith("chumpy."):
            return _stand_in(_Chumpy, module, name)
        if module in _SPARSE_MODULES and name in _SPARSE_CLASSES:
            return _stand_in(_Sparse, module, name)
        raise StatfitError(f"refusing to load {module}.{name} from a pickle (only arrays, chumpy arrays and "
                           "sparse matrices are allowed)")


def load_pickle(path: str | Path) -> Any:
    """The object in the pickle at ``path`` with chumpy arrays as numpy arrays and sparse matrices
    as scipy matrices; arbitrary code in the pickle is refused (StatfitError), never run."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise StatfitError(f"cannot read {path}: {exc.strerror}") from None
    try:
        loaded = _RestrictedUnpickler(io.BytesIO(data), encoding="latin1").load()
    except StatfitError as exc:
        raise StatfitError(f"{path}: {exc}") from None
    except Exception as exc:  # a damaged or truncated pickle raises many kinds
        raise StatfitError(f"cannot read {path}: not a valid pickle ({type(exc).__name__}: {exc})") from None
    return _resolve(loaded, path)


def _resolve(value: Any, path: str | Path) -> Any:
    """Replace stand-ins by arrays, recursively through dicts, lists and tuples."""
    if isinstance(value, dict):
        return {key: _resolve(item, path) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_resolve(item, path) for item in value)
    if isinstance(value, _Chumpy):
        if not isinstance(value.state, dict) or "x" not in value.state:
            raise StatfitError(f"{path}: a chumpy {value.source} without a stored value cannot be read "
                               "without chumpy (only plain Ch arrays are supported)")
        return np.asarray(_resolve(value.state["x"], path))
    if isinstance(value, _Sparse):
        return _sparse(value, path)
    if isinstance(value, _Pickled):
        raise StatfitError(f"{path}: cannot read a pickled {value.source}")
    return value


def _sparse(value: _Sparse, path: str | Path) -> scipy.sparse.spmatrix:
    """A scipy sparse matrix from the pickled state of a csc/csr/coo matrix."""
    state = value.state if isinstance(value.state, dict) else {}
    shape = state.get("_shape", state.get("shape"))
    try:
        if value.source.endswith(("coo_matrix", "coo_array")):
            coords = (state["row"], state["col"]) if "row" in state else tuple(state["coords"])
            return scipy.sparse.coo_matrix((state["data"], coords), shape=shape)
        build = scipy.sparse.csc_matrix if "csc" in value.source.rsplit(".", 1)[1] else scipy.sparse.csr_matrix
        return build((state["data"], state["indices"], state["indptr"]), shape=shape)
    except (KeyError, TypeError, ValueError) as exc:
        raise StatfitError(f"{path}: a pickled {value.source} is damaged ({type(exc).__name__}: {exc})") from None
