"""Preview image of an inverse-rendering fit: target normals | fitted normals | angular error
(with a colour bar) | the fitted mesh turned 70° | the fitted mesh from behind (what the map never saw).
The last two show the mesh's normals, or a per-vertex field (``data_distance``, ``off_span``,
``observed``: where the fit guessed) in colour with its bar."""
from __future__ import annotations

import io

import numpy as np
import torch

from statfit.renderer import Camera, interpolate, rasterize
from statfit.renderer.images import render_target

SIDE_VIEW_DEG = 70.0
BACK_VIEW_DEG = 180.0
PREVIEW_COLOURS = ("normals", "data_distance", "off_span", "observed")


def normals_to_rgb(normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Camera-space (OpenCV) unit normals (H, W, 3) → RGB in the usual look of normal maps
    (OpenGL axes: +x red, +y up green, +z towards the viewer blue); background white."""
    rgb = (normals * np.array([1.0, -1.0, -1.0]) + 1.0) / 2.0
    return np.where(mask[..., None], np.clip(rgb, 0.0, 1.0), 1.0)


def angular_error(fitted: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Angle in degrees between unit normals (H, W, 3), per pixel."""
    cosine = np.clip((fitted * target).sum(axis=-1), -1.0, 1.0)
    return np.degrees(np.arccos(cosine))


def side_camera(camera: Camera, vertices: np.ndarray, degrees: float = SIDE_VIEW_DEG) -> Camera:
    """``camera`` turned by ``degrees`` about its own vertical axis through the mesh's centroid."""
    centre = vertices.mean(axis=0)
    angle = np.radians(degrees)
    turn = np.array([[np.cos(angle), 0.0, np.sin(angle)], [0.0, 1.0, 0.0], [-np.sin(angle), 0.0, np.cos(angle)]])
    R, t = camera.rotation.numpy(), camera.world_to_camera[:3, 3].numpy()
    centre_cam = R @ centre + t
    pose = np.eye(4)
    pose[:3, :3] = turn @ R
    pose[:3, 3] = centre_cam - turn @ R @ centre
    return Camera(camera.width, camera.height, camera.K, pose)


def field_image(vertices: np.ndarray, faces: np.ndarray, camera: Camera, values: np.ndarray) -> np.ndarray:
    """Per-vertex ``values`` (N,) interpolated over the mesh as ``camera`` sees it, (H, W), NaN
    on the background."""
    points, face_ids = torch.as_tensor(vertices, dtype=torch.float64), torch.as_tensor(faces, dtype=torch.long)
    fragments = rasterize(points, face_ids, camera)
    image = interpolate(torch.as_tensor(values, dtype=torch.float64)[:, None], face_ids, fragments)[..., 0]
    return np.where((fragments.triangle >= 0).numpy(), image.numpy(), np.nan)


def preview_png(target: np.ndarray, target_mask: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                camera: Camera, colour: tuple[str, np.ndarray] | None = None) -> bytes:
    """The preview as PNG bytes. target: camera-space (OpenCV) normals (H, W, 3) and mask (H, W).
    ``colour``: (name, per-vertex values (N,)) to colour the two other views by, instead of normals."""
    if colour is not None:
        return _coloured(preview_figure(target, target_mask, vertices, faces, camera), vertices, faces, camera,
                         *colour)
    return _png(preview_figure(target, target_mask, vertices, faces, camera))


def _pyplot():
    """matplotlib's pyplot on its file-only backend, imported when a figure is drawn: a command that
    draws none (and `batch report`, which uses this module's pixel functions) does not pay its 0.4 s."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def preview_figure(target: np.ndarray, target_mask: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                   camera: Camera):
    """The preview's matplotlib figure (five panels)."""
    fitted, covered = render_target(vertices, faces, camera, space="camera")
    both = covered & target_mask
    error = np.where(both, angular_error(fitted, target), np.nan)
    side, side_mask = render_target(vertices, faces, side_camera(camera, vertices), space="camera")
    back, back_mask = render_target(vertices, faces, side_camera(camera, vertices, BACK_VIEW_DEG), space="camera")
    figure, axes = _pyplot().subplots(1, 5, figsize=(20, 4.4), constrained_layout=True)
    axes[0].imshow(normals_to_rgb(target, target_mask))
    axes[0].set_title("target normals")
    axes[1].imshow(normals_to_rgb(fitted, covered))
    axes[1].set_title("fitted normals")
    heat = axes[2].imshow(error, cmap="inferno", vmin=0.0, vmax=max(float(np.nanpercentile(error, 99)), 1.0)
                          if both.any() else 1.0)
    mean = float(np.nanmean(error)) if both.any() else float("nan")
    axes[2].set_title(f"angular error (mean {mean:.1f}°)")
    figure.colorbar(heat, ax=axes[2], fraction=0.046, pad=0.02, label="degrees")
    axes[3].imshow(normals_to_rgb(side, side_mask))
    axes[3].set_title(f"fitted mesh, view turned {SIDE_VIEW_DEG:.0f}°")
    axes[4].imshow(normals_to_rgb(back, back_mask))
    axes[4].set_title("fitted mesh, from behind")
    for axis in axes:
        axis.set_axis_off()
    return figure


def _coloured(figure, vertices: np.ndarray, faces: np.ndarray, camera: Camera, name: str, values: np.ndarray) -> bytes:
    """The figure's two other views redrawn coloured by the per-vertex ``values`` (N,)."""
    values = np.asarray(values, dtype=np.float64)
    finite = values[np.isfinite(values)]
    top = max(float(np.percentile(finite, 99)) if finite.size else 1.0, 1e-12)
    for axis, degrees, label in ((figure.axes[3], SIDE_VIEW_DEG, f"view turned {SIDE_VIEW_DEG:.0f}°"),
                                 (figure.axes[4], BACK_VIEW_DEG, "from behind")):
        axis.images[0].remove()
        shown = axis.imshow(field_image(vertices, faces, side_camera(camera, vertices, degrees), values),
                            cmap="viridis", vmin=0.0, vmax=top)
        axis.set_title(f"{name}, {label}")
    figure.colorbar(shown, ax=figure.axes[4], fraction=0.046, pad=0.02, label=name)
    return _png(figure)


def _png(figure) -> bytes:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=80)
    _pyplot().close(figure)
    return buffer.getvalue()
