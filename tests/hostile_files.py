"""A corpus of hostile and careless input files, generated (nothing binary is checked in): each is
named for what is wrong with it and says which command reads it, and how.

``write_corpus(folder, good)`` writes every file into ``folder`` and returns ``{name: argv}`` with
``OUT`` standing for the folder a run may write into; ``good`` holds valid inputs to pair with
(``scan``, ``normals``, ``camera``, ``image``, ``mask``, ``gt``).
"""
from __future__ import annotations

import io
import json
import pickle
import struct
import zipfile
import zlib
from pathlib import Path

import numpy as np


def _png(width: int, height: int, payload: bytes = b"") -> bytes:
    """A PNG whose header declares ``width`` × ``height`` RGB pixels, with ``payload`` as its data."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(payload)) + chunk(b"IEND", b""))


def _npz(members: dict[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return buffer.getvalue()


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.lib.format.write_array(buffer, array, allow_pickle=True)
    return buffer.getvalue()


def _npy_claiming(shape: tuple[int, ...]) -> bytes:
    """An .npy header claiming ``shape`` float64 followed by 8 bytes of data."""
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": "<f8", "fortran_order": False, "shape": shape})
    return buffer.getvalue() + b"\0" * 8


class _Payload:
    """Unpickling this runs code (writes a marker file): a pickle that must never be loaded."""

    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _ply(rows: list[tuple[float, float, float]], declared: int | None = None) -> bytes:
    header = (f"ply\nformat ascii 1.0\nelement vertex {len(rows) if declared is None else declared}\n"
              "property float x\nproperty float y\nproperty float z\nend_header\n")
    return (header + "".join(f"{x} {y} {z}\n" for x, y, z in rows)).encode()


def _exr_with_window(source: bytes, width: int, height: int) -> bytes:
    """``source`` (a small EXR) with its data window patched to ``width`` × ``height``."""
    key = b"dataWindow\0box2i\0" + struct.pack("<i", 16)
    start = source.index(key) + len(key)
    return source[:start] + struct.pack("<4i", 0, 0, width - 1, height - 1) + source[start + 16:]


def write_corpus(folder: Path, good: dict[str, Path]) -> dict[str, list[str]]:
    """Write the hostile files into ``folder``; ``{name: argv}`` of the run that reads each."""
    rng = np.random.default_rng(7)
    noise = rng.bytes(4096)
    points = [tuple(p) for p in rng.normal(size=(50, 3)) * 0.1]
    files: dict[str, tuple[str, bytes | None]] = {
        # scans (register SCAN)
        "scan-empty.ply": ("scan", b""),
        "scan-random-bytes.ply": ("scan", noise),
        "scan-header-only.ply": ("scan", _ply([])[:60]),
        "scan-truncated.ply": ("scan", _ply(points)[:-400]),
        "scan-nan.ply": ("scan", _ply([(float("nan"), 0.0, 0.0)] + points)),
        "scan-inf.ply": ("scan", _ply([(float("inf"), 0.0, 0.0)] + points)),
        "scan-three-points.ply": ("scan", _ply(points[:3])),
        "scan-declares-a-trillion.ply": ("scan", _ply(points, declared=10**12)),
        "scan-text.obj": ("scan", b"this is not a mesh\n" * 20),
        "scan-garbage.stl": ("scan", noise[:300]),
        "scan-bad.off": ("scan", b"OFF\n3 1 0\n0 0 0\n1 1\n"),
        "scan-unknown-suffix.xyz": ("scan", b"0 0 0\n"),
        "scan-png-inside.ply": ("scan", _png(4, 4, b"\0" * 52)),
        "scan-one-far-point.ply": ("scan", _ply([(1e30, 1e30, 1e30)] * 12)),
        "scan-a-folder.ply": ("scan", None),
        # models (register SCAN --model MODEL)
        "model-empty.npz": ("model", b""),
        "model-random.npz": ("model", noise),
        "model-truncated.npz": ("model", _npz({"v_template.npy": _npy(np.zeros((4, 3)))})[:-30]),
        "model-claims-3e12-values.npz": ("model", _npz({"v_template.npy": _npy_claiming((10**6, 3, 10**6)),
                                                        "faces.npy": _npy(np.zeros((1, 3), np.int64)),
                                                        "shapedirs.npy": _npy(np.zeros((4, 3, 1)))})),
        "model-object-array.npz": ("model", _npz({"v_template.npy": _npy(np.array([None, {}], dtype=object))})),
        "model-missing-keys.npz": ("model", _npz({"v_template.npy": _npy(np.zeros((4, 3)))})),
        "model-nan-template.npz": ("model", _npz({"v_template.npy": _npy(np.full((4, 3), np.nan)),
                                                  "faces.npy": _npy(np.array([[0, 1, 2], [0, 2, 3]])),
                                                  "shapedirs.npy": _npy(np.ones((4, 3, 2)))})),
        "model-mismatched-shapes.npz": ("model", _npz({"v_template.npy": _npy(np.zeros((4, 3))),
                                                       "faces.npy": _npy(np.array([[0, 1, 9]])),
                                                       "shapedirs.npy": _npy(np.ones((5, 3, 2)))})),
        "model-pickle-runs-code.pkl": ("model", pickle.dumps(_Payload(str(folder / "PWNED")))),
        "model-random.pkl": ("model", noise),
        "model-garbage.h5": ("model", b"\x89HDF\r\n\x1a\n" + noise[:200]),
        "model-a-folder": ("model", None),
        # normal maps (render MAP --camera CAMERA)
        "normals-empty.exr": ("normals", b""),
        "normals-random.exr": ("normals", b"v/1\x01" + noise),
        "normals-png-inside.exr": ("normals", _png(8, 8, b"\0" * 200)),
        "normals-text.exr": ("normals", b"not an exr\n"),
        # cameras (render GOOD_MAP --camera CAMERA)
        "camera-empty.json": ("camera", b""),
        "camera-not-json.json": ("camera", b"{width: 3"),
        "camera-a-list.json": ("camera", b"[1, 2, 3]"),
        "camera-missing-K.json": ("camera", json.dumps({"width": 48, "height": 48}).encode()),
        "camera-singular-K.json": ("camera", json.dumps({"width": 48, "height": 48, "K": [[0] * 3] * 3,
                                                         "world_to_camera": np.eye(4).tolist()}).encode()),
        "camera-nan-K.json": ("camera", json.dumps({"width": 48, "height": 48,
                                                    "K": [[float("nan")] * 3] * 3,
                                                    "world_to_camera": np.eye(4).tolist()}).encode()),
        "camera-wrong-size.json": ("camera", json.dumps({"width": 7, "height": 9, "K": np.eye(3).tolist(),
                                                         "world_to_camera": np.eye(4).tolist()}).encode()),
        "camera-strings.json": ("camera", json.dumps({"width": "wide", "height": None, "K": "eye"}).encode()),
        "camera-binary.json": ("camera", noise[:100]),
        # images and masks (inpaint IMAGE --mask MASK)
        "image-empty.png": ("image", b""),
        "image-random.png": ("image", noise),
        "image-truncated.png": ("image", _png(24, 24, rng.bytes(24 * 73))[:-40]),
        "image-bomb-20000x20000.png": ("image", _png(20000, 20000)),
        "image-header-9000x9000.png": ("image", _png(9000, 9000)),
        "image-text.jpg": ("image", b"JFIF? no.\n"),
        "image-a-folder.png": ("image", None),
        "mask-empty.png": ("mask", b""),
        "mask-bomb-20000x20000.png": ("mask", _png(20000, 20000)),
        "mask-random.png": ("mask", noise),
        "mask-other-size.png": ("mask", _png(5, 7, b"".join(b"\0" + b"\xff" * 15 for _ in range(7)))),
        # landmarks (register SCAN --landmarks FILE)
        "landmarks-empty.txt": ("landmarks", b""),
        "landmarks-text.txt": ("landmarks", b"nose tip\nchin\n"),
        "landmarks-wrong-count.txt": ("landmarks", b"0 0 0\n1 1 1\n"),
        "landmarks-all-nan.txt": ("landmarks", b"nan nan nan\n" * 10),
        "landmarks-inf.txt": ("landmarks", b"inf 0 0\n" * 10),
        "landmarks-ragged.txt": ("landmarks", b"0 0\n1 1 1 1\n"),
        "landmarks-binary.txt": ("landmarks", noise[:500]),
        # texture models (inpaint IMAGE --mask MASK --model FILE)
        "texture-random.npz": ("texture", noise),
        "texture-claims-3e12-values.npz": ("texture", _npz({"v_template.npy": _npy_claiming((10**12, 3))})),
        "texture-a-mesh-model.npz": ("texture", (Path(__file__).resolve().parents[1] / "data_templates"
                                                 / "default_head.npz").read_bytes()),
        # meshes (eval FIT GT)
        "fit-points-only.ply": ("fit", _ply(points)),
        "fit-nan.ply": ("fit", _ply([(float("nan"), 0, 0)] * 3)[:-1] + b"\n"),
    }
    exr = good["normals"].read_bytes()
    files["normals-window-100000x100000.exr"] = ("normals", _exr_with_window(exr, 100_000, 100_000))
    files["normals-window-negative.exr"] = ("normals", _exr_with_window(exr, -5, 3))
    files["normals-truncated.exr"] = ("normals", exr[: len(exr) // 2])
    g = {k: str(v) for k, v in good.items()}
    argv = {
        "scan": lambda f: ["register", f, "--out", "OUT/fit.ply", "--iterations", "2", "-q"],
        "model": lambda f: ["register", g["scan"], "--model", f, "--out", "OUT/fit.ply", "--iterations", "2", "-q"],
        "normals": lambda f: ["render", f, "--camera", g["camera"], "--out", "OUT/fit.ply", "--iterations", "2", "-q"],
        "camera": lambda f: ["render", g["normals"], "--camera", f, "--out", "OUT/fit.ply", "--iterations", "2", "-q"],
        "image": lambda f: ["inpaint", f, "--mask", g["mask"], "--out", "OUT/o.png", "--iterations", "2", "-q"],
        "mask": lambda f: ["inpaint", g["image"], "--mask", f, "--out", "OUT/o.png", "--iterations", "2", "-q"],
        "landmarks": lambda f: ["register", g["scan"], "--landmarks", f, "--out", "OUT/fit.ply", "--iterations", "2",
                                "-q"],
        "texture": lambda f: ["inpaint", g["image"], "--mask", g["mask"], "--model", f, "--out", "OUT/o.png",
                              "--iterations", "2", "-q"],
        "fit": lambda f: ["eval", f, g["gt"], "--json"],
    }
    runs = {}
    for name, (kind, data) in files.items():
        path = folder / name
        if data is None:
            path.mkdir()
        else:
            path.write_bytes(data)
        runs[name] = argv[kind](str(path))
    return runs

