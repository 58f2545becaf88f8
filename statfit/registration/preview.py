"""Preview image of a registration (``statfit register --preview``): the scan's points over the fit,
seen from the model's front (green on the fit's surface to red where the fit misses them), then the
fit from the front, turned 70° and from behind, coloured by a per-vertex field — by default
``data_distance``, the distance to the nearest scan point: near zero where the scan saw the surface,
large where the fit guessed — with its colour bar, or shaded by its normals."""
from __future__ import annotations

import numpy as np

from statfit.geometry.metrics import measured_points, surface_distance
from statfit.io.figures import figure_png, pyplot
from statfit.renderer.images import (FAR_SHARE, field_image, field_top, front_camera, mesh_with_points,
                                     normals_to_rgb, render_target, turned_camera)

VIEW = 320                  # pixels: each view's side
VIEWS = ((0.0, "front"), (70.0, "turned 70°"), (180.0, "from behind"))
UNITS = {"data_distance": "scan units", "off_span": "scan units", "observed": "1: seen, 0: guessed"}


def register_preview_png(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, turn: np.ndarray,
                         colour: tuple[str, np.ndarray] | None) -> bytes:
    """PNG bytes of the four panels. vertices (N, 3), faces (F, 3): the fit, in the scan's frame;
    points (M, 3): the scan; turn (3, 3): the model → scan similarity's linear part (where the
    model's front faces); colour: (name, per-vertex values (N,)) to colour the fit by, or None
    for its normals."""
    points = measured_points(points)
    distance = surface_distance(points, vertices, faces)
    front = front_camera(vertices, turn, VIEW)
    figure, axes = pyplot().subplots(1, 4, figsize=(17, 4.4), constrained_layout=True)
    axes[0].imshow(mesh_with_points(vertices, faces, points, distance, front)[0])
    axes[0].set_title(f"scan on the fit\ndistance median {np.median(distance):.3g}, mean {distance.mean():.3g}\n"
                      f"(green on it, red {FAR_SHARE:.0%} of its radius off)")
    if colour is not None:
        name, values = colour[0], np.asarray(colour[1], dtype=np.float64)
        top = field_top(values)
    for axis, (degrees, label) in zip(axes[1:], VIEWS):
        camera = turned_camera(front, vertices, degrees)
        if colour is None:
            normals, covered = render_target(vertices, faces, camera, space="camera")
            axis.imshow(normals_to_rgb(normals, covered))
            axis.set_title(f"fit, {label}")
        else:
            shown = axis.imshow(field_image(vertices, faces, camera, values), cmap="viridis", vmin=0.0, vmax=top)
            axis.set_title(f"{name}, {label}")
    if colour is not None:
        figure.colorbar(shown, ax=axes[3], fraction=0.046, pad=0.02, label=f"{name} ({UNITS.get(name, '')})")
    for axis in axes:
        axis.set_axis_off()
    return figure_png(figure)
