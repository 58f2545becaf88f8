"""Colour PNGs written from the PNG specification (RFC 2083), independently of Pillow, which cannot
write 16-bit colour: every scanline filter type and Adam7 interlacing, so a reader is tried on what
other tools (libpng, OpenCV, normal estimators) write. 8-bit files of the same code check it against
Pillow's reader."""
from __future__ import annotations

import struct
import zlib

import numpy as np

# Adam7: (first column, first row, column step, row step) of each pass.
ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))


def png_bytes(samples: np.ndarray, interlaced: bool = False) -> bytes:
    """``samples`` (H, W, 3 or 4) uint16 (or uint8) as a 16-bit (8-bit) RGB or RGBA PNG; scanline r
    filtered with type r mod 5 (None, Sub, Up, Average, Paeth)."""
    height, width, channels = samples.shape
    bits = 8 * samples.dtype.itemsize
    colour_type = {3: 2, 4: 6}[channels]
    passes = ADAM7 if interlaced else ((0, 0, 1, 1),)
    data = b"".join(_filtered(samples[y0::dy, x0::dx]) for x0, y0, dx, dy in passes)
    header = struct.pack(">IIBBBBB", width, height, bits, colour_type, 0, 0, int(interlaced))
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(data)) + _chunk(b"IEND", b"")


def _filtered(image: np.ndarray) -> bytes:
    """The scanlines of ``image`` (h, w, C) uint16 or uint8, each a filter-type byte and its
    filtered bytes."""
    height, width, channels = image.shape
    if height == 0 or width == 0:
        return b""
    step = image.dtype.itemsize * channels                                # bytes a pixel
    x = image.astype(image.dtype.newbyteorder(">")).view(np.uint8).reshape(height, width * step).astype(np.int64)
    a = np.pad(x, ((0, 0), (step, 0)))[:, :-step]                         # the byte a pixel to the left
    b = np.pad(x, ((1, 0), (0, 0)))[:-1]                                  # the byte above
    c = np.pad(b, ((0, 0), (step, 0)))[:, :-step]                         # above and to the left
    p = a + b - c
    pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - c)
    paeth = np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))
    predictions = np.stack([np.zeros_like(x), a, b, (a + b) // 2, paeth])  # (5, h, w·step)
    kind = np.arange(height) % 5
    rows = (x - predictions[kind, np.arange(height)]) % 256
    return np.concatenate([kind[:, None], rows], axis=1).astype(np.uint8).tobytes()


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
