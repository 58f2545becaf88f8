"""Synthetic test data: a model sample (plus an optional off-model delta) seen from one side, as a
partial scan or as a normal map."""
from __future__ import annotations

import numpy as np
import trimesh

from statfit.errors import StatfitError
from statfit.io.npz import read_npz
from statfit.structures.frame import Frame, surface_vertices
from statfit.model.statmodel import StatModel
from statfit.structures.camera import Camera


def sample_target(model: StatModel, rng: np.random.Generator, sigma: float = 1.0,
                  delta: np.ndarray | None = None, delta_weight: float = 1.0) -> np.ndarray:
    """Vertices (N, 3): a random model shape (coefficients ~ N(0, sigma²)) plus ``delta_weight·delta``."""
    shape = model.sample(rng, sigma)
    if delta is not None:
        if delta.shape != shape.shape:
            raise StatfitError(f"delta has shape {delta.shape}, the model has {shape.shape}")
        shape = shape + delta_weight * delta
    return shape


def load_delta(path: str, name: str) -> np.ndarray:
    """One named delta (N, 3) from an npz with ``names (D,)`` and ``deltas (N, 3, D)``."""
    data = read_npz(path, "delta")
    if "names" not in data or "deltas" not in data:
        raise StatfitError(f"cannot read deltas from {path}: it needs the keys names and deltas")
    names, deltas = [str(n) for n in data["names"]], data["deltas"]
    if name not in names:
        raise StatfitError(f"{path} has no delta named {name!r}; it has {', '.join(names[:8])}...")
    return deltas[..., names.index(name)].astype(np.float64)


def view_direction(yaw_deg: float, pitch_deg: float = 0.0) -> np.ndarray:
    """Unit vector from the object towards the viewer; yaw 0, pitch 0 looks along −z (at the +z face)."""
    yaw, pitch = np.radians(yaw_deg), np.radians(pitch_deg)
    return np.array([np.sin(yaw) * np.cos(pitch), np.sin(pitch), np.cos(yaw) * np.cos(pitch)])


def scan_from_view(vertices: np.ndarray, faces: np.ndarray, rng: np.random.Generator, num_points: int = 4300,
                   yaw_deg: float = 30.0, pitch_deg: float = 0.0, noise: float = 0.0,
                   outliers: float = 0.0) -> np.ndarray:
    """Points of the surface visible from one direction (orthographic ray casting), subsampled to
    ``num_points``; ``noise`` is Gaussian noise relative to the shape's RMS radius and
    ``outliers`` the fraction of points replaced by uniform points in the bounding box."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    toward_viewer = view_direction(yaw_deg, pitch_deg)
    right = np.cross([0.0, 1.0, 0.0], toward_viewer)
    right = right / np.linalg.norm(right) if np.linalg.norm(right) > 1e-8 else np.array([1.0, 0.0, 0.0])
    up = np.cross(toward_viewer, right)
    surface = surface_vertices(vertices, faces)
    frame = Frame.of(surface)
    local = (surface - frame.center) @ np.stack([right, up]).T
    lo, hi = local.min(axis=0), local.max(axis=0)
    side = int(np.ceil(np.sqrt(8 * num_points)))
    a, b = np.meshgrid(np.linspace(lo[0], hi[0], side), np.linspace(lo[1], hi[1], side))
    origins = frame.center + a.reshape(-1, 1) * right + b.reshape(-1, 1) * up + 4 * frame.scale * toward_viewer
    directions = np.broadcast_to(-toward_viewer, origins.shape)
    hits, _, _ = mesh.ray.intersects_location(origins, directions, multiple_hits=False)
    if len(hits) < num_points:
        raise StatfitError(f"only {len(hits)} surface points are visible; ask for fewer than {num_points}")
    points = hits[rng.choice(len(hits), num_points, replace=False)]
    points = points + rng.normal(scale=noise * frame.scale, size=points.shape)
    count = int(round(outliers * num_points))
    if count:
        box_lo, box_hi = surface.min(axis=0), surface.max(axis=0)
        points[rng.choice(num_points, count, replace=False)] = rng.uniform(box_lo, box_hi, size=(count, 3))
    return points


def camera_for_view(vertices: np.ndarray, yaw_deg: float = 20.0, pitch_deg: float = 0.0, size: int = 512,
                    fov_deg: float = 30.0, fill: float = 0.85) -> Camera:
    """A square pinhole camera looking at the shape's centroid from ``view_direction(yaw, pitch)``,
    +y up, far enough that the shape's bounding sphere spans ``fill`` of the image height."""
    if size < 8:
        raise StatfitError(f"image size must be at least 8 pixels, got {size}")
    if not 0.0 < fill <= 1.0:
        raise StatfitError(f"fill must lie in (0, 1], got {fill}")
    centre = vertices.mean(axis=0)
    radius = float(np.linalg.norm(vertices - centre, axis=1).max())
    distance = radius / np.sin(np.radians(fov_deg) / 2 * fill)
    eye = centre + distance * view_direction(yaw_deg, pitch_deg)
    return Camera.look_at(eye, centre, [0.0, 1.0, 0.0], fov_deg, size, size)
