"""Writers of small model files in each source format's real layout (keys, dtypes, nesting), for tests."""
from __future__ import annotations

import io
import pickle
import sys
import types
from contextlib import contextmanager
from pathlib import Path

import h5py
import numpy as np
import scipy.sparse


class Ch:
    """Pickles like chumpy's ``chumpy.ch.Ch``: protocol 2 NEWOBJ of ``chumpy.ch.Ch`` and, as state,
    the instance dict without the weak-reference caches (chumpy's ``__getstate__``)."""

    def __init__(self, x: np.ndarray):
        self.x = x
        self._dirty_vars = set()
        self._itr = None
        self._depends_on_deps = {}

    def __getstate__(self) -> dict:
        return dict(self.__dict__)


@contextmanager
def fake_chumpy():
    """``chumpy.ch.Ch`` importable while pickling, so the bytes name it exactly as real files do."""
    package, module = types.ModuleType("chumpy"), types.ModuleType("chumpy.ch")
    Ch.__module__, Ch.__qualname__ = "chumpy.ch", "Ch"
    module.Ch, package.ch = Ch, module
    saved = {name: sys.modules.get(name) for name in ("chumpy", "chumpy.ch")}
    sys.modules.update({"chumpy": package, "chumpy.ch": module})
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                sys.modules.pop(name)
            else:
                sys.modules[name] = value


def random_smpl_arrays(rng: np.random.Generator, n: int = 60, k: int = 400) -> dict:
    """A small FLAME/SMPL-X-like dict: template on a sphere, triangle fan faces, skinning keys."""
    template = rng.standard_normal((n, 3))
    template /= np.linalg.norm(template, axis=1, keepdims=True) * 10
    faces = np.stack([np.zeros(n - 2, int), np.arange(1, n - 1), np.arange(2, n)], axis=1).astype(np.uint32)
    shapedirs = rng.standard_normal((n, 3, k)) * 1e-3 / np.sqrt(1 + np.arange(k))
    return {"v_template": template, "f": faces, "shapedirs": shapedirs,
            "posedirs": rng.standard_normal((n, 3, 36)) * 1e-3,
            "J_regressor": scipy.sparse.random(5, n, density=0.2, format="csc", random_state=0),
            "weights": np.full((n, 5), 0.2), "kintree_table": np.array([[2**32 - 1, 0, 1, 1, 1], [0, 1, 2, 3, 4]]),
            "J": rng.standard_normal((5, 3)), "bs_style": "lbs", "bs_type": "lrotmin"}


class Python2Pickler(pickle._Pickler):
    """Writes bytes and text as Python 2 ``str`` (SHORT_BINSTRING / BINSTRING opcodes), as the
    chumpy-era FLAME and SMPL pickles hold their keys and array buffers, instead of Python 3's
    unicode strings and ``_codecs.encode`` calls."""

    def save_py2_str(self, obj: bytes) -> None:
        size = len(obj)
        header = pickle.SHORT_BINSTRING + bytes([size]) if size < 256 else pickle.BINSTRING + size.to_bytes(4, "little")
        self.write(header + obj)  # not memoised: short bytes are shared objects, so ids repeat

    def save_text_as_py2_str(self, obj: str) -> None:
        self.save_py2_str(obj.encode("latin1"))

    dispatch = dict(pickle._Pickler.dispatch)
    dispatch[bytes] = save_py2_str
    dispatch[str] = save_text_as_py2_str


# Module paths of numpy 1.x and scipy < 1.8, which the distributed pickles name.
OLD_MODULES = {b"numpy._core.multiarray\n": b"numpy.core.multiarray\n", b"scipy.sparse._csc\n": b"scipy.sparse.csc\n"}


def write_flame_pickle(path: Path, arrays: dict, style: str = "2020") -> Path:
    """FLAME 2020 style (``2020``: shapedirs and J as chumpy Ch, protocol 2; ``2020-py2``: the same
    with Python-2 strings and numpy 1.x / old scipy module paths) or 2023 style (plain numpy)."""
    data = dict(arrays)
    if style == "2023":
        path.write_bytes(pickle.dumps(data, protocol=4))
        return path
    with fake_chumpy():
        data["shapedirs"], data["J"] = Ch(arrays["shapedirs"]), Ch(arrays["J"])
        buffer = io.BytesIO()
        (Python2Pickler if style == "2020-py2" else pickle.Pickler)(buffer, protocol=2).dump(data)
    raw = buffer.getvalue()
    if style == "2020-py2":
        for new, old in OLD_MODULES.items():
            raw = raw.replace(new, old)
    path.write_bytes(raw)
    return path


def write_flame_masks(path: Path, masks: dict[str, np.ndarray]) -> Path:
    """FLAME_masks.pkl layout: a Python-2 pickle of a dict region name → vertex index array."""
    buffer = io.BytesIO()
    Python2Pickler(buffer, protocol=2).dump(masks)
    path.write_bytes(buffer.getvalue().replace(*next(iter(OLD_MODULES.items()))))
    return path


def write_bfm_h5(path: Path, mean: np.ndarray, basis: np.ndarray, variance: np.ndarray, faces: np.ndarray,
                 expression: tuple[np.ndarray, np.ndarray] | None = None) -> Path:
    """BFM 2017 layout: float32 shape/model/{mean (3N,), pcaBasis (3N, K), pcaVariance (K,)},
    shape/representer/{points (3, N), cells (3, F)}, and the optional expression group."""
    with h5py.File(path, "w") as handle:
        groups = {"shape": (basis, variance)} | ({"expression": expression} if expression else {})
        for group, (b, v) in groups.items():
            handle[f"{group}/model/mean"] = (mean if group == "shape" else np.zeros_like(mean)).astype(np.float32)
            handle[f"{group}/model/pcaBasis"] = b.astype(np.float32)
            handle[f"{group}/model/pcaVariance"] = v.astype(np.float32)
            handle[f"{group}/model/noiseVariance"] = np.float32(1e-6)
            handle[f"{group}/representer/points"] = mean.reshape(-1, 3).T.astype(np.float32)
            handle[f"{group}/representer/cells"] = faces.T.astype(np.uint32)
    return path


def write_obj(path: Path, vertices: np.ndarray, polygons: np.ndarray | None = None) -> None:
    """An OBJ with texture coordinates on every face corner (like ICT-FaceKit's), 1-based indices."""
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in vertices]
    if polygons is not None:
        lines += [f"vt {u:.4f} 0.5" for u in np.linspace(0, 1, len(vertices))]
        lines += ["f " + " ".join(f"{i + 1}/{i + 1}" for i in polygon) for polygon in polygons]
    path.write_text("\n".join(lines) + "\n")


def write_ict_folder(folder: Path, neutral: np.ndarray, polygons: np.ndarray, identities: np.ndarray) -> Path:
    """generic_neutral_mesh.obj and identity000.obj … (``identities`` (K, N, 3) meshes)."""
    folder.mkdir(parents=True, exist_ok=True)
    write_obj(folder / "generic_neutral_mesh.obj", neutral, polygons)
    for i, mesh in enumerate(identities):
        write_obj(folder / f"identity{i:03d}.obj", mesh, polygons)
    return folder
