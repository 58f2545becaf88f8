"""Low-level OpenEXR reading and writing shared by normal maps and images: channels as float32
arrays, the header as a dict, damaged files as one-line errors, writes atomic."""
from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np
import OpenEXR

from statfit.errors import StatfitError
from statfit.io.files import existing_file, write_atomic

EXR_MAGIC = b"\x76\x2f\x31\x01"


# The most values (pixels × channels) read from one EXR: an 8192² RGBA map. Larger headers are
# refused before any pixel is decoded.
MAX_VALUES = 1 << 28

@contextmanager
def _quiet_stderr() -> Iterator[None]:
    """Silence the OpenEXR C library, which prints its own messages on failures."""
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def is_exr(path: str | Path) -> bool:
    """Whether the file starts with the OpenEXR magic number."""
    with open(path, "rb") as handle:
        return handle.read(4) == EXR_MAGIC


def read_exr(path: str | Path, what: str = "file") -> tuple[dict, dict[str, np.ndarray]]:
    """Header and channels (name → (H, W) float32) of the EXR at ``path``; ``what`` names the file
    in messages (``normal map``, ``image``)."""
    path = existing_file(path, what)
    if not is_exr(path):
        raise StatfitError(f"{path} is not an OpenEXR file")
    try:
        with _quiet_stderr(), OpenEXR.File(str(path), header_only=True) as exr:
            low, high = (np.asarray(corner) for corner in exr.header()["dataWindow"])
            width, height = (int(v) for v in high - low + 1)
            layers = len(exr.channels()) or 1
    except Exception as exc:  # the bindings raise RuntimeError and friends for damaged files
        raise StatfitError(f"cannot read {path}: damaged OpenEXR file ({exc})") from None
    if width <= 0 or height <= 0 or width * height * layers > MAX_VALUES:
        raise StatfitError(f"{what} {path} declares {width}×{height} pixels × {layers} channels; statfit reads at "
                           f"most {MAX_VALUES:,} values")
    try:
        with _quiet_stderr(), OpenEXR.File(str(path), separate_channels=True) as exr:
            header = dict(exr.header())
            channels = {name: np.asarray(ch.pixels, dtype=np.float32) for name, ch in exr.channels().items()}
    except Exception as exc:  # the bindings raise RuntimeError and friends for damaged files
        raise StatfitError(f"cannot read {path}: damaged OpenEXR file ({exc})") from None
    return header, channels


def exr_bytes(channels: dict[str, np.ndarray], header: dict | None = None) -> bytes:
    """Float channels (name → (H, W)) encoded as a ZIP-compressed scanline EXR; ``header`` adds
    attributes."""
    full = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage} | (header or {})
    channels = {name: np.ascontiguousarray(data, dtype=np.float32) for name, data in channels.items()}
    with tempfile.TemporaryDirectory() as scratch:
        staging = Path(scratch) / "image.exr"
        with OpenEXR.File(full, channels) as exr:
            exr.write(str(staging))
        return staging.read_bytes()


def write_exr(path: str | Path, channels: dict[str, np.ndarray], header: dict | None = None) -> None:
    """Write float channels (name → (H, W)) as a ZIP-compressed scanline EXR, atomically."""
    write_atomic(path, exr_bytes(channels, header))
