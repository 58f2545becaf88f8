"""Preview image of an inverse-rendering fit: target normals | fitted normals | angular error
(with a colour bar) | the fitted mesh turned 70° | the fitted mesh from behind (what the map never saw).
The last two show the mesh's normals, or a per-vertex field (``data_distance``, ``off_span``,
``observed``: where the fit guessed) in colour with its bar."""
from __future__ import annotations

import numpy as np

from statfit.io.figures import figure_png, pyplot
from statfit.renderer import Camera
from statfit.renderer.images import field_image, field_top, normals_to_rgb, render_target, turned_camera

SIDE_VIEW_DEG = 70.0
BACK_VIEW_DEG = 180.0


def angular_error(fitted: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Angle in degrees between unit normals (H, W, 3), per pixel."""
    cosine = np.clip((fitted * target).sum(axis=-1), -1.0, 1.0)
    return np.degrees(np.arccos(cosine))


def preview_png(target: np.ndarray, target_mask: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                camera: Camera, colour: tuple[str, np.ndarray] | None = None) -> bytes:
    """The preview as PNG bytes. target: camera-space (OpenCV) normals (H, W, 3) and mask (H, W).
    ``colour``: (name, per-vertex values (N,)) to colour the two other views by, instead of normals."""
    if colour is not None:
        return _coloured(preview_figure(target, target_mask, vertices, faces, camera), vertices, faces, camera,
                         *colour)
    return figure_png(preview_figure(target, target_mask, vertices, faces, camera))


def preview_figure(target: np.ndarray, target_mask: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                   camera: Camera):
    """The preview's matplotlib figure (five panels)."""
    fitted, covered = render_target(vertices, faces, camera, space="camera")
    both = covered & target_mask
    error = np.where(both, angular_error(fitted, target), np.nan)
    side, side_mask = render_target(vertices, faces, turned_camera(camera, vertices, SIDE_VIEW_DEG), space="camera")
    back, back_mask = render_target(vertices, faces, turned_camera(camera, vertices, BACK_VIEW_DEG), space="camera")
    figure, axes = pyplot().subplots(1, 5, figsize=(20, 4.4), constrained_layout=True)
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
    top = field_top(values)
    for axis, degrees, label in ((figure.axes[3], SIDE_VIEW_DEG, f"view turned {SIDE_VIEW_DEG:.0f}°"),
                                 (figure.axes[4], BACK_VIEW_DEG, "from behind")):
        axis.images[0].remove()
        shown = axis.imshow(field_image(vertices, faces, turned_camera(camera, vertices, degrees), values),
                            cmap="viridis", vmin=0.0, vmax=top)
        axis.set_title(f"{name}, {label}")
    figure.colorbar(shown, ax=figure.axes[4], fraction=0.046, pad=0.02, label=name)
    return figure_png(figure)
