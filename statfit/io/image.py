"""Images in and out: PNG/JPG (Pillow, 8 or 16 bit) and OpenEXR (float), grey, RGB or RGBA, as
float32 arrays (H, W, C) in [0, 1]; masks and UV-chart label images as (H, W) arrays.

8-bit values v map to v / 255 and back by rounding, so an 8-bit image survives a round trip
exactly; 16-bit values v map to v / 65535; EXR values are kept as they are (float, not clipped on
reading).

Pillow has no 16-bit colour mode: it decodes a 16-bit RGB(A) PNG to 8 bits a sample (a normal map
of a person the model makes, read so, fits ~29% worse than from its 16 bits: docs/studies.md §38).
Such a file is decoded twice here, once keeping each big-endian sample's high byte (Pillow's own
rawmode) and once its low byte (the little-endian rawmode, which keeps the byte at the sample's
second place), and the two put together.
"""
from __future__ import annotations

import io
import struct
import warnings
import zlib
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from statfit.errors import StatfitError
from statfit.io.exr import exr_bytes, is_exr, read_exr
from statfit.io.files import existing_file, write_atomic

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr")
EXR_CHANNELS = {1: "Y", 3: "RGB", 4: "RGBA"}


# A mask pixel is on above half grey (8-bit).
MASK_THRESHOLD = 127
# The most pixels an image may declare (8192²: 0.8 GB as float32 RGB); larger headers are refused
# before anything is decoded.
MAX_PIXELS = 1 << 26

def read_image(path: str | Path) -> np.ndarray:
    """An image as float32 (H, W, C) with C = 1 (grey), 3 (RGB) or 4 (RGBA); values in [0, 1]
    for 8/16-bit files. Palette and grey-with-alpha images become RGB(A)."""
    path = existing_file(path, "image")
    if path.stat().st_size == 0:
        raise StatfitError(f"{path} is empty")
    image = _read_exr(path) if is_exr(path) else _read_pillow(path)
    if not np.isfinite(image).all():
        bad = int((~np.isfinite(image)).any(axis=-1).sum())
        raise StatfitError(f"{path} has NaN or infinite values on {bad} pixels")
    return image


def _read_pillow(path: Path) -> np.ndarray:
    return _opened(path, "image", _decoded)


def _opened(path: Path, what: str, decode) -> np.ndarray:
    """``decode(image, path)`` of the image file at ``path``, opened with Pillow; unreadable files
    and headers declaring more than ``MAX_PIXELS`` (decompression bombs) are refused in one line."""
    existing_file(path, what)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(path) as image:
                if image.width * image.height > MAX_PIXELS:
                    raise StatfitError(f"{what} {path} declares {image.width}×{image.height} pixels, more than "
                                       f"the {MAX_PIXELS:,} statfit reads")
                return decode(image, path)
    except (OSError, ValueError, UnidentifiedImageError, Image.DecompressionBombWarning,
            Image.DecompressionBombError) as exc:
        raise StatfitError(f"cannot read {what} {path}: {exc}") from None


# The rawmode of a 16-bit colour PNG's samples (big-endian) → the rawmode reading their low bytes.
LOW_BYTES = {"RGB;16B": "RGB;16L", "RGBA;16B": "RGBA;16L"}
# Pillow's modes of a 16-bit grey image.
SIXTEEN_BIT_GREY = ("I;16", "I;16B", "I;16L", "I")


def _decoded(image: Image.Image, path: Path) -> np.ndarray:
    """The opened ``image`` decoded to float32 (H, W, C)."""
    rawmode = _png_rawmode(image)
    if rawmode in LOW_BYTES:
        return _sixteen_bit_colour(image, path, rawmode)
    image.load()
    if image.mode in SIXTEEN_BIT_GREY:
        return (np.asarray(image, dtype=np.float32) / 65535.0)[..., None]
    if image.mode not in ("L", "RGB", "RGBA"):
        image = image.convert("RGBA" if "A" in image.getbands() or "transparency" in image.info else "RGB")
    data = np.asarray(image, dtype=np.float32) / 255.0
    return data[..., None] if data.ndim == 2 else data


def _png_rawmode(image: Image.Image) -> str | None:
    """How Pillow will unpack an opened PNG's samples (e.g. 'RGB;16B'); None for other files."""
    if image.format != "PNG" or len(image.tile) != 1:
        return None
    args = image.tile[0][3]
    return args if isinstance(args, str) else None


def _sixteen_bit_colour(image: Image.Image, path: Path, rawmode: str) -> np.ndarray:
    """A 16-bit RGB(A) PNG, opened as ``image`` (its samples ``rawmode``), at all its 16 bits:
    float32 (H, W, C), v / 65535."""
    image.load()
    high = np.asarray(image, dtype=np.uint16)
    with Image.open(path) as again:
        codec, extents, offset, _ = again.tile[0]
        again.tile = [(codec, extents, offset, LOW_BYTES[rawmode])]
        again.load()
        low = np.asarray(again, dtype=np.uint16)
    return ((high << 8) | low).astype(np.float32) / 65535.0


def _read_exr(path: Path) -> np.ndarray:
    _, channels = read_exr(path, "image")
    for names in ("RGBA", "RGB", "Y"):
        if all(c in channels for c in names):
            return np.stack([channels[c] for c in names], axis=-1)
    raise StatfitError(f"{path} has neither R, G, B nor Y channels; it has {', '.join(sorted(channels)) or 'none'}")


def image_bytes(image: np.ndarray, suffix: str, bits: int = 8) -> bytes:
    """``image`` (H, W, C) in [0, 1] encoded as PNG (``bits`` 8 or 16 a sample) or 8-bit JPEG
    (``suffix`` .png/.jpg/.jpeg; values are clipped; JPEG drops alpha)."""
    if suffix == ".png" and bits == 16:
        return png16_bytes(np.round(np.clip(image, 0.0, 1.0) * 65535.0).astype(np.uint16))
    data = np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)
    data = data[..., 0] if data.shape[-1] == 1 else data
    if suffix == ".png":
        fmt, options = "PNG", {}
    else:
        fmt, options = "JPEG", {"quality": 95}
        if data.ndim == 3 and data.shape[-1] == 4:
            data = data[..., :3]
    buffer = io.BytesIO()
    Image.fromarray(data).save(buffer, format=fmt, **options)
    return buffer.getvalue()


# PNG colour types by channels: grey, RGB, RGBA.
PNG_COLOUR_TYPES = {1: 0, 3: 2, 4: 6}


def png16_bytes(samples: np.ndarray) -> bytes:
    """A 16-bit PNG of ``samples`` (H, W, C) uint16, C in 1/3/4 (Pillow writes no 16-bit colour):
    the PNG specification's IHDR, one zlib stream of big-endian rows each filtered by "Up" (its bytes
    less the row above's, mod 256: a smooth texture's file half the size of unfiltered rows'), IEND."""
    height, width, channels = samples.shape
    raw = samples.astype(">u2").reshape(height, -1).view(np.uint8)
    rows = np.full((height, 1 + raw.shape[1]), 2, dtype=np.uint8)          # filter type 2 (Up) a row
    rows[:, 1:] = raw
    rows[1:, 1:] -= raw[:-1]

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, 16, PNG_COLOUR_TYPES[channels], 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows.tobytes(), 6))
            + chunk(b"IEND", b""))


def sample_bits(path: str | Path) -> int:
    """Bits a sample of the image file at ``path``: 8, 16 (a 16-bit PNG) or 32 (float EXR)."""
    path = Path(path)
    if is_exr(path):
        return 32
    return _opened(path, "image", lambda image, _: 16 if _png_rawmode(image) in LOW_BYTES
                   or image.mode in SIXTEEN_BIT_GREY else 8)


def encoded_image(image: np.ndarray, suffix: str, bits: int = 8) -> bytes:
    """``image`` (H, W, C), C in 1/3/4, as the bytes of a file: float EXR for ``.exr``, else PNG
    (``bits`` 8 or 16 a sample) or 8-bit JPEG (:func:`image_bytes`)."""
    if image.ndim != 3 or image.shape[-1] not in EXR_CHANNELS:
        raise StatfitError(f"cannot write an image of shape {image.shape}: need (H, W, 1, 3 or 4)")
    if suffix == ".exr":
        return exr_bytes({c: image[..., i] for i, c in enumerate(EXR_CHANNELS[image.shape[-1]])})
    return image_bytes(image, suffix, bits)


def write_image(path: str | Path, image: np.ndarray) -> None:
    """Write ``image`` (H, W, C) atomically, encoded by the file's suffix (:func:`encoded_image`)."""
    write_atomic(path, encoded_image(image, image_suffix(path)))


def image_suffix(path: str | Path) -> str:
    """The path's lower-case suffix if it is an image format statfit writes, else a StatfitError."""
    suffix = Path(path).suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise StatfitError(f"{path}: unsupported image format {suffix!r}; use one of {', '.join(IMAGE_SUFFIXES)}")
    return suffix


def _read_grey_or_rgb(path: str | Path, what: str, mode: str) -> np.ndarray:
    return _opened(Path(path), what, lambda image, _: np.asarray(image.convert(mode)))


def read_mask(path: str | Path) -> np.ndarray:
    """A mask (H, W) bool from an image file (PNG, ...): white (> 50% grey) is True (foreground,
    or visible)."""
    return _read_grey_or_rgb(path, "mask", "L") > MASK_THRESHOLD


def read_charts(path: str | Path) -> np.ndarray:
    """UV-chart labels (H, W) int64 from an image: black is outside every chart (0); every other
    colour is one chart (1, 2, … in order of colour value). A black-and-white mask is one label."""
    rgb = _read_grey_or_rgb(path, "chart image", "RGB").astype(np.int64)
    packed = (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]
    colours, labels = np.unique(packed, return_inverse=True)
    labels = labels.reshape(packed.shape) + (0 if colours[0] == 0 else 1)
    return labels
