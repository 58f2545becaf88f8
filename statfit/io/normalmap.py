"""Normal maps (OpenEXR, or PNG as other tools write them) and cameras (JSON, or an EXR header) in
and out.

EXR channels R, G, B hold a unit normal per pixel and A the coverage mask (1 foreground, 0
background); half or float. A render's normal pass is read too, as Blender's multilayer EXRs name
it: '<view layer>.Normal.X', '.Y', '.Z' (world space), the coverage its layer's 'Combined.A'.
Without A, pixels with a zero-length normal are background. An EXR holding (n + 1) / 2 per channel,
as a PNG does (some bakers and converters write float images so), is read as a PNG is, with a
warning: its foreground values all lie in [0, 1], they decode to unit normals and are not unit
themselves (no map of unit normals is all three). A camera may travel in the header as the standard
``worldToCamera`` attribute (4×4) plus a ``K`` (3×3).

A PNG (8- or 16-bit, :func:`statfit.io.image.read_image`) holds (n + 1) / 2 per channel, the way
normal estimators and bakers save normal maps; a pixel is foreground where its alpha (if any) is over
half and its decoded normal is within ``PNG_UNIT_TOLERANCE`` of unit length: black and white
backgrounds decode to length √3, mid-grey to 0, and 8-bit rounding moves a true normal's length by
less than 0.02. A PNG carries no camera (``--camera``).
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np

from statfit.errors import StatfitError, StatfitWarning
from statfit.io.exr import is_exr, read_exr, write_exr
from statfit.io.files import existing_file, write_atomic
from statfit.io.image import read_image
from statfit.structures.camera import Camera
from statfit.structures.normal_map import NormalMap

PNG_UNIT_TOLERANCE = 0.1
# An EXR's foreground whose values lie within ENCODED_SLACK of [0, 1], of which at least ENCODED_SHARE
# (of the pixels not decoding to about zero: a grey background) decodes as (n + 1) / 2 to unit normals
# (within PNG_UNIT_TOLERANCE) while its stored normals' median length is off 1 by more than
# PNG_UNIT_TOLERANCE, holds encoded normals.
ENCODED_SLACK = 1e-3
ENCODED_SHARE = 0.5


def read_normal_map(path: str | Path) -> NormalMap:
    """Read and validate a normal map: an EXR, or a PNG named ``.png`` (the module's docstring)."""
    path = existing_file(path, "normal map")
    if path.suffix.lower() == ".png" and not is_exr(path):
        return _read_png(path)
    header, channels = read_exr(path, "normal map")
    if (names := _normal_channels(channels)) is None:
        missing = [c for c in "RGB" if c not in channels]
        raise StatfitError(f"{path} has no {'/'.join(missing)} channel(s) nor a render's Normal.X/Y/Z pass; it has "
                           f"{', '.join(sorted(channels)) or 'none'}")
    xyz, alpha = names
    normals = np.stack([channels[c] for c in xyz], axis=-1)
    length = np.linalg.norm(normals, axis=-1)
    mask = channels[alpha] > 0.5 if alpha is not None else length > 0
    if (decoded := _decoded_colour(normals, mask)) is not None:
        warnings.warn(f"{path}: its values lie in [0, 1] and decode as (n + 1) / 2 to unit normals: read as a "
                      "PNG normal map's are (an EXR normal map holds the unit normals themselves)", StatfitWarning,
                      stacklevel=2)
        normals, length, unit = decoded
        mask = mask & unit
    return NormalMap(*_validated(normals, length, mask, path), camera=_header_camera(header, normals.shape))


def _normal_channels(channels: dict[str, np.ndarray]) -> tuple[list[str], str | None] | None:
    """The names of the channels holding the normals and the coverage (None: none): R, G, B (A); or
    a render's normal pass as Blender's multilayer EXRs name it, '<view layer>.Normal.X', '.Y', '.Z',
    its coverage the same layer's 'Combined.A' (or a plain A). None where neither, or several
    layers, are there."""
    if all(c in channels for c in "RGB"):
        return list("RGB"), "A" if "A" in channels else None
    layers = [name[: -len("Normal.X")] for name in channels
              if name.endswith("Normal.X") and all(name[:-1] + axis in channels for axis in "YZ")]
    if len(layers) != 1:
        return None
    layer = layers[0]
    alpha = next((name for name in (f"{layer}Combined.A", "A") if name in channels), None)
    return [f"{layer}Normal.{axis}" for axis in "XYZ"], alpha


def _decoded_colour(normals: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """For an EXR map ``normals`` (H, W, 3) holding (n + 1) / 2 per channel on ``mask`` (H, W): the
    decoded normals, their lengths and whether each is unit (H, W); None for any other map."""
    values = normals[mask]
    if values.size == 0 or values.min() < -ENCODED_SLACK or values.max() > 1.0 + ENCODED_SLACK:
        return None
    decoded, length, unit = _decoded(normals)
    stored = np.linalg.norm(normals[mask & unit], axis=-1)
    # A grey background (0.5 each) decodes to length 0: not counted either way.
    if ((mask & unit).sum() < ENCODED_SHARE * (mask & (length > 0.5)).sum() or stored.size == 0
            or np.median(np.abs(stored - 1.0)) <= PNG_UNIT_TOLERANCE):
        return None
    return decoded, length, unit


def _decoded(colours: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Colours (H, W, 3) holding (n + 1) / 2 decoded: the normals, their lengths and whether each
    is unit within PNG_UNIT_TOLERANCE (H, W)."""
    normals = colours * 2.0 - 1.0
    length = np.linalg.norm(normals, axis=-1)
    return normals, length, np.abs(length - 1.0) < PNG_UNIT_TOLERANCE


def _read_png(path: Path) -> NormalMap:
    """A PNG normal map: (n + 1) / 2 per channel, coverage from alpha and the decoded length."""
    image = read_image(path)
    if image.shape[-1] < 3:
        raise StatfitError(f"{path}: a PNG normal map is RGB or RGBA, (n + 1) / 2 per channel; this one is grey")
    normals, length, mask = _decoded(image[..., :3])
    if image.shape[-1] == 4:
        mask &= image[..., 3] > 0.5
    return NormalMap(*_validated(normals, length, mask, path))


def apply_mask(normal_map: NormalMap, mask: np.ndarray, source: str) -> NormalMap:
    """The same normal map with ``mask`` (H, W) bool replacing its coverage."""
    if mask.shape != normal_map.mask.shape:
        raise StatfitError(f"{source} is {mask.shape[1]}×{mask.shape[0]} but the normal map is "
                           f"{normal_map.mask.shape[1]}×{normal_map.mask.shape[0]}")
    normals, mask = _validated(normal_map.normals, np.linalg.norm(normal_map.normals, axis=-1), mask, source)
    return NormalMap(normals, mask, normal_map.camera)


def _validated(normals: np.ndarray, length: np.ndarray, mask: np.ndarray, source) -> tuple[np.ndarray, np.ndarray]:
    if not mask.any():
        raise StatfitError(f"{source}: the mask has no foreground pixel")
    if not np.isfinite(normals[mask]).all():
        raise StatfitError(f"{source} has NaN or infinite normals on {int((~np.isfinite(normals[mask])).any(-1).sum())} "
                           "foreground pixels")
    if (length[mask] < 1e-6).any():
        raise StatfitError(f"{source} has zero-length normals on {int((length[mask] < 1e-6).sum())} foreground pixels")
    unit = np.where(mask[..., None], normals / np.maximum(length, 1e-12)[..., None], 0.0)
    return unit.astype(np.float32), mask


def _header_camera(header: dict, shape: tuple[int, ...]) -> Camera | None:
    if "worldToCamera" not in header or "K" not in header:
        return None
    return Camera(shape[1], shape[0], np.asarray(header["K"]), np.asarray(header["worldToCamera"]))


def check_camera_fits(camera: Camera, normal_map: NormalMap, source: str) -> None:
    """Refuse a camera whose image size differs from the normal map's."""
    height, width = normal_map.mask.shape
    if (camera.width, camera.height) != (width, height):
        raise StatfitError(f"{source} is for a {camera.width}×{camera.height} image but the normal map is "
                           f"{width}×{height}")


def camera_for_map(normal_map: NormalMap, camera_path: str | Path | None, source: str | Path) -> Camera:
    """The camera of a normal map read from ``source``: from ``camera_path`` (JSON) if given,
    checked against the map's size, else from the map's header."""
    if camera_path is not None:
        camera = read_camera(camera_path)
        check_camera_fits(camera, normal_map, str(camera_path))
        return camera
    if normal_map.camera is None:
        raise StatfitError(f"{source} carries no camera in its header; pass --camera camera.json")
    return normal_map.camera


def write_normal_map(path: str | Path, normals: np.ndarray, mask: np.ndarray, camera: Camera | None = None) -> None:
    """Write normals (H, W, 3) and mask (H, W) as a float EXR (R, G, B, A), atomically; with
    ``camera``, its K and world_to_camera go into the header."""
    header = {}
    if camera is not None:
        header["K"] = camera.K.numpy().astype(np.float32)
        header["worldToCamera"] = camera.world_to_camera.numpy().astype(np.float32)
    channels = {c: normals[..., i] for i, c in enumerate("RGB")}
    channels["A"] = mask.astype(np.float32)
    write_exr(path, channels, header)


def read_camera(path: str | Path) -> Camera:
    """A camera from its JSON description (docs/formats.md)."""
    path = existing_file(path, "camera file")
    try:
        data = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise StatfitError(f"{path} is not valid JSON: {exc}") from None
    return Camera.from_dict(data)


def write_camera(path: str | Path, camera: Camera) -> None:
    """Write ``camera`` as JSON, atomically."""
    write_atomic(path, (json.dumps(camera.to_dict(), indent=1) + "\n").encode())
