"""Multi-view folders: photographs with their cameras, the input of ``statfit splat``.

A folder holds the images (any format :func:`statfit.io.image.read_image` reads) and
``cameras.json``::

    {"format": "statfit-views", "version": 1,
     "views": [{"image": "view_000.png", "split": "train", "camera": {<Camera.to_dict()>},
                "mask": "view_000_mask.png"}, ...],
     "gt": "gt.ply"}

``split`` is "train" (the default) or "test"; ``mask`` is optional (grey > 50% is foreground) and
wins over an RGBA image's alpha (alpha > 0.5 is foreground); an RGB or grey image without a mask
has none. ``gt`` (a ground-truth mesh for evaluation) is optional and not read here. File names
are relative to the folder; absolute names and names leading out of it (``..``, symbolic links)
are refused, so nothing outside the folder is ever read.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from statfit.structures.camera import Camera
from statfit.errors import StatfitError
from statfit.io.files import existing_file, existing_folder
from statfit.io.image import read_image, read_mask
from statfit.structures.views import SPLITS, View

CAMERAS_FILE = "cameras.json"
FORMAT = "statfit-views"
VERSION = 1
MAX_VIEWS = 1000
MAX_JSON_BYTES = 16 << 20
# All views' pixels together (2²⁸: 3 GiB as float32 RGB; 1000 views of 512², 250 of 1024²).
MAX_TOTAL_PIXELS = 1 << 28
def read_views(folder: str | Path) -> list[View]:
    """The views of a multi-view folder, in the order of its ``cameras.json``; every problem is
    one :class:`StatfitError` line naming the file or view. The whole file is checked before any
    image is read."""
    folder = existing_folder(folder, "views folder")
    source = folder / CAMERAS_FILE
    entries = _entries(_json(source), source)
    described = [_described(entry, index, source) for index, entry in enumerate(entries)]
    _check_sizes(described, source)
    if not any(split == "train" for _, _, split in described):
        raise StatfitError(f"{source}: no view has split 'train'")
    return [_view(folder, entry, name, camera, split, source)
            for entry, (name, camera, split) in zip(entries, described)]


def views_json(entries: list[tuple[str, Camera, str]], gt: str | None = None) -> bytes:
    """``cameras.json`` for (image name, camera, split) triples, with the ground-truth mesh's name
    ``gt`` if given; pretty-printed, ending in a newline."""
    data: dict[str, Any] = {"format": FORMAT, "version": VERSION,
                            "views": [{"image": name, "split": split, "camera": camera.to_dict()}
                                      for name, camera, split in entries]}
    if gt is not None:
        data["gt"] = gt
    return (json.dumps(data, indent=1) + "\n").encode()


def _json(path: Path) -> Any:
    """The parsed JSON of ``path``, refused when empty, larger than ``MAX_JSON_BYTES`` or not JSON."""
    path = existing_file(path, "views file")
    try:
        with path.open("rb") as handle:
            data = handle.read(MAX_JSON_BYTES + 1)
    except OSError as exc:
        raise StatfitError(f"cannot read {path}: {exc.strerror}") from None
    if not data:
        raise StatfitError(f"{path} is empty")
    if len(data) > MAX_JSON_BYTES:
        raise StatfitError(f"{path} is larger than {MAX_JSON_BYTES >> 20} MiB; refusing it")
    try:
        return json.loads(data)
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError is a ValueError
        raise StatfitError(f"{path} is not valid JSON: {' '.join(str(exc).split())[:200]}") from None


def _entries(data: Any, source: Path) -> list[Any]:
    """The ``views`` list of the parsed file, its format, version and length checked."""
    if not isinstance(data, dict) or not isinstance(data.get("views"), list):
        raise StatfitError(f'{source} must be a JSON object with a "views" list')
    if data.get("format", FORMAT) != FORMAT or data.get("version", VERSION) != VERSION:
        raise StatfitError(f'{source}: expected "format": "{FORMAT}", "version": {VERSION}; got '
                           f'{str(data.get("format"))[:40]!r}, version {str(data.get("version"))[:20]}')
    entries = data["views"]
    if not entries:
        raise StatfitError(f"{source} has no views")
    if len(entries) > MAX_VIEWS:
        raise StatfitError(f"{source} has {len(entries):,} views; statfit reads at most {MAX_VIEWS:,}")
    return entries


def _described(entry: Any, index: int, source: Path) -> tuple[str, Camera, str]:
    """Image name, camera and split of view number ``index``, its entry checked."""
    if not isinstance(entry, dict):
        raise StatfitError(f"{source}: view {index} is not a JSON object")
    missing = [key for key in ("image", "camera") if key not in entry]
    if missing:
        raise StatfitError(f"{source}: view {index} lacks {' and '.join(missing)}")
    name = entry["image"]
    if not isinstance(name, str) or not name:
        raise StatfitError(f"{source}: view {index}: image must be a file name")
    split = entry.get("split", "train")
    if split not in SPLITS:
        raise StatfitError(f"{source}: view {name}: split must be 'train' or 'test', got {str(split)[:40]!r}")
    try:
        return name, Camera.from_dict(entry["camera"]), split
    except StatfitError as exc:
        raise StatfitError(f"{source}: view {name}: {exc}") from None


def _check_sizes(described: list[tuple[str, Camera, str]], source: Path) -> None:
    """Refuse cameras of different image sizes, or more pixels in all than ``MAX_TOTAL_PIXELS``,
    before any image is read."""
    first_name, first, _ = described[0]
    for name, camera, _ in described:
        if (camera.width, camera.height) != (first.width, first.height):
            raise StatfitError(f"{source}: all views must have the same size; view {name} is "
                               f"{camera.width}×{camera.height}, view {first_name} {first.width}×{first.height}")
    if len(described) * first.width * first.height > MAX_TOTAL_PIXELS:
        raise StatfitError(f"{source}: {len(described)} views of {first.width}×{first.height} pixels are more "
                           f"than the {MAX_TOTAL_PIXELS:,} pixels statfit reads")


def _view(folder: Path, entry: dict, name: str, camera: Camera, split: str, source: Path) -> View:
    """The view ``name`` of ``entry``: its image (and mask) read from ``folder`` and checked
    against ``camera``."""
    pixels = read_image(_inside(folder, name, name, source))
    height, width = pixels.shape[:2]
    if (width, height) != (camera.width, camera.height):
        raise StatfitError(f"{source}: view {name}: the image is {width}×{height} but its camera "
                           f"{camera.width}×{camera.height}")
    image = np.clip(np.repeat(pixels, 3, axis=-1) if pixels.shape[-1] == 1 else pixels[..., :3], 0.0, 1.0)
    mask = _mask(folder, entry, name, pixels, source)
    if mask is not None and not mask.any():
        raise StatfitError(f"{source}: view {name}: the mask is empty")
    return View(name, camera, np.ascontiguousarray(image, dtype=np.float32), mask, split)


def _mask(folder: Path, entry: dict, name: str, pixels: np.ndarray, source: Path) -> np.ndarray | None:
    """The mask (H, W) bool of view ``name``: the mask file its entry names, else the image's
    alpha > 0.5, else None. ``pixels`` (H, W, C) is the image as read."""
    if entry.get("mask") is None:
        return pixels[..., 3] > 0.5 if pixels.shape[-1] == 4 else None
    if not isinstance(entry["mask"], str) or not entry["mask"]:
        raise StatfitError(f"{source}: view {name}: mask must be a file name")
    mask = read_mask(_inside(folder, entry["mask"], name, source))
    if mask.shape != pixels.shape[:2]:
        raise StatfitError(f"{source}: view {name}: the mask is {mask.shape[1]}×{mask.shape[0]} but the image "
                           f"{pixels.shape[1]}×{pixels.shape[0]}")
    return mask


def _inside(folder: Path, relative: str, view: str, source: Path) -> Path:
    """``folder / relative``, refused when ``relative`` is absolute or leads out of ``folder``."""
    path = folder / relative
    try:
        escapes = Path(relative).is_absolute() or not path.resolve().is_relative_to(folder.resolve())
    except (OSError, ValueError, RuntimeError):  # a NUL byte, a symbolic-link loop, too long a name
        escapes = True
    if escapes:
        raise StatfitError(f"{source}: view {view}: {relative[:80]!r} is not a file name inside the folder")
    return path
