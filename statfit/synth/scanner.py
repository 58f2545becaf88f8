"""A simulated range scanner: realistic test scans of a model sample.

A real scan is not a clean sample of the template's surface. This module builds one as a range
scanner would: the shape plus clutter the template does not cover (a neck and shoulders tube
below it, a hair layer over the scalp that hides it), seen along a grid of parallel rays from one
side, with the surfaces at grazing angles lost, a few holes, depth noise, the grid's hits joined
into a triangle mesh (so the density varies with the view angle, as it does in a scan), and the
whole moved into its own pose and units. Models follow the usual frame: +y up, +z the face.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from statfit.geometry.align import Similarity
from statfit.errors import StatfitError
from statfit.structures.frame import Frame, surface_vertices
from statfit.synth.sample import view_direction
from statfit.synth.scan_options import CLUTTER_PARTS, SCAN_UNITS_PER_METRE, UNITS_PER_METRE

# Hits whose surface turns away from the rays beyond this (cosine) are lost, as in a real scanner.
GRAZING_COSINE = 0.2
# Two neighbouring grid hits are joined only if their depths differ by less than this many grid steps.
DEPTH_JUMP_STEPS = 4.0
# The hair layer's thickness and the tube's length, in the shape's RMS radii.
HAIR_THICKNESS = 0.08
TUBE_LENGTH = 1.2


@dataclass(frozen=True)
class RealisticScan:
    """A simulated scan: its mesh ``vertices`` (V, 3) and ``faces`` (F, 3) in the scan's frame and
    units, ``on_shape`` (V,) whether each vertex lies on the shape (not clutter), the shape's
    vertices ``truth`` (N, 3) in the scan's frame, and ``transform`` (shape frame → scan frame)."""

    vertices: np.ndarray
    faces: np.ndarray
    on_shape: np.ndarray
    truth: np.ndarray
    transform: Similarity

    @property
    def clutter_ratio(self) -> float:
        """Clutter vertices per shape vertex."""
        return float((~self.on_shape).sum() / max(int(self.on_shape.sum()), 1))


def model_units(template: np.ndarray) -> float:
    """The model's length unit as a multiple of a metre, guessed from a head's size (0.1–0.5 m)."""
    extent = float(np.ptp(template, axis=0).max())
    for units in UNITS_PER_METRE.values():
        if 0.1 <= extent / units <= 0.5:
            return units
    return 1.0


def neck_tube(vertices: np.ndarray, rings: int = 40, sectors: int = 72) -> trimesh.Trimesh:
    """An open tube below the shape, flaring into shoulders: the ellipse of the shape's lowest
    vertices continued downwards for TUBE_LENGTH radii (outward normals)."""
    frame = Frame.of(vertices)
    low = vertices[:, 1].min()
    ring = vertices[vertices[:, 1] < low + 0.15 * frame.scale]
    centre = ring.mean(axis=0)
    radius_x, radius_z = np.ptp(ring[:, 0]) / 2, np.ptp(ring[:, 2]) / 2
    t = np.linspace(0.0, 1.0, rings)[:, None]
    angle = np.linspace(0.0, 2 * np.pi, sectors, endpoint=False)[None, :]
    flare = np.clip((t - 0.35) / 0.4, 0, 1) ** 2
    x = centre[0] + radius_x * (1 + 2.2 * flare) * np.cos(angle)
    z = centre[2] + radius_z * (1 + 0.5 * flare) * np.sin(angle)
    y = np.broadcast_to(low + 0.1 * frame.scale - TUBE_LENGTH * frame.scale * t, x.shape)
    points = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(rings - 1), np.arange(sectors), indexing="ij")
    a, b = i * sectors + j, i * sectors + (j + 1) % sectors
    c, d = a + sectors, b + sectors
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return trimesh.Trimesh(points, faces, process=False)


def hair_layer(vertices: np.ndarray, faces: np.ndarray, rng: np.random.Generator) -> trimesh.Trimesh:
    """The shape's scalp (top and back, not the face) lifted off along its normals by a bumpy
    HAIR_THICKNESS radii: a surface a scanner sees instead of the scalp."""
    frame = Frame.of(vertices, faces)
    u = frame.to_unit(vertices)
    scalp = ((u[:, 1] > 0.35) & (u[:, 2] < 0.35)) | ((u[:, 1] > -0.2) & (u[:, 2] < -0.45))
    keep = scalp[faces].all(axis=1)
    if not keep.any():
        raise StatfitError("the shape has no scalp to put hair on (is +y its up axis?)")
    normals = trimesh.Trimesh(vertices, faces, process=False).vertex_normals
    waves = rng.normal(size=(3, 3))
    bumps = 1 + 0.3 * np.sin(u @ waves).sum(axis=1) / 3
    lifted = vertices + (HAIR_THICKNESS * frame.scale * bumps)[:, None] * normals
    used, remap = np.unique(faces[keep], return_inverse=True)
    return trimesh.Trimesh(lifted[used], remap.reshape(-1, 3), process=False)


def _grid_mesh(cells: np.ndarray, depth: np.ndarray, shape: tuple[int, int], step: float) -> np.ndarray:
    """Triangles (F, 3) over hits at grid ``cells`` (V, 2) with ``depth`` (V,): two per grid square
    whose corners were hit, skipping depth jumps (silhouettes); wound to face the viewer."""
    index = np.full(shape, -1)
    index[cells[:, 0], cells[:, 1]] = np.arange(len(cells))
    p00, p10, p01, p11 = index[:-1, :-1], index[1:, :-1], index[:-1, 1:], index[1:, 1:]
    triangles = np.concatenate([np.stack([p00, p10, p01], -1).reshape(-1, 3),
                                np.stack([p10, p11, p01], -1).reshape(-1, 3)])
    triangles = triangles[(triangles >= 0).all(axis=1)]
    d = depth[triangles]
    return triangles[np.ptp(d, axis=1) < DEPTH_JUMP_STEPS * step]


def realistic_scan(vertices: np.ndarray, faces: np.ndarray, rng: np.random.Generator, points: int = 4300,
                   yaw_deg: float = 30.0, pitch_deg: float = 0.0, clutter: float = 0.5, holes: int = 3,
                   noise: float = 0.002, units: str = "mm", posed: bool = True,
                   clutter_parts: tuple[str, ...] = CLUTTER_PARTS) -> RealisticScan:
    """A range scan of the shape (``vertices`` (N, 3), ``faces`` (F, 3), +y up) seen from
    ``view_direction(yaw, pitch)``, with about ``points`` points on the shape; ``clutter`` the
    clutter points per shape point wanted (hair, then as much neck and shoulders as it takes; 0:
    none), ``holes`` disks of lost data, ``noise`` the depth noise in RMS radii, ``units`` the
    scan's length unit (mm, cm, m, in; the model's is guessed from its size), ``posed`` a rotation
    uniform over all rotations plus an offset, and ``clutter_parts`` which clutter there is (of
    CLUTTER_PARTS; without ``neck``, the hair is all the clutter)."""
    if units not in SCAN_UNITS_PER_METRE:
        raise StatfitError(f"unknown units {units!r}; choose one of {', '.join(SCAN_UNITS_PER_METRE)}")
    if not 0 <= clutter <= 2:
        raise StatfitError(f"clutter must lie in [0, 2] (clutter points per shape point), got {clutter}")
    if unknown := set(clutter_parts) - set(CLUTTER_PARTS):
        raise StatfitError(f"unknown clutter part(s) {', '.join(sorted(unknown))}; choose from {', '.join(CLUTTER_PARTS)}")
    frame = Frame.of(vertices, faces)
    parts, ids = [trimesh.Trimesh(vertices, faces, process=False)], [0]    # 0 shape, 1 hair, 2 tube
    if clutter > 0 and "hair" in clutter_parts:
        parts, ids = parts + [hair_layer(vertices, faces, rng)], ids + [1]
    if clutter > 0 and "neck" in clutter_parts:
        parts, ids = parts + [neck_tube(surface_vertices(vertices, faces))], ids + [2]
    scene = trimesh.util.concatenate(parts)
    owner = np.repeat(ids, [len(p.faces) for p in parts])

    toward = view_direction(yaw_deg, pitch_deg)
    right = np.cross([0.0, 1.0, 0.0], toward)
    right = right / np.linalg.norm(right) if np.linalg.norm(right) > 1e-8 else np.array([1.0, 0.0, 0.0])
    up = np.cross(toward, right)
    axes = np.stack([right, up])
    shape_2d = (vertices - frame.center) @ axes.T
    step = float(np.sqrt(0.75 * np.prod(np.ptp(shape_2d, axis=0)) / points))
    scene_2d = (scene.vertices - frame.center) @ axes.T
    lo, hi = scene_2d.min(axis=0) - step, scene_2d.max(axis=0) + step
    grid = tuple(int(n) for n in np.ceil((hi - lo) / step) + 1)
    a, b = np.meshgrid(lo[0] + step * np.arange(grid[0]), lo[1] + step * np.arange(grid[1]), indexing="ij")
    origins = frame.center + a.reshape(-1, 1) * right + b.reshape(-1, 1) * up + 8 * frame.scale * toward
    hits, ray, triangle = scene.ray.intersects_location(origins, np.broadcast_to(-toward, origins.shape),
                                                        multiple_hits=False)
    cells = np.stack(np.unravel_index(ray, grid), axis=1)
    part = owner[triangle]
    keep = np.abs(scene.face_normals[triangle] @ toward) > GRAZING_COSINE
    for _ in range(holes):   # disks of lost data, centred on the shape
        centre = cells[rng.choice(np.flatnonzero(part == 0))]
        radius = rng.uniform(0.03, 0.08) * frame.scale / step
        keep &= np.linalg.norm(cells - centre, axis=1) > radius
    if clutter > 0:          # as much of the tube (from the top down) as makes up the clutter wanted
        shape_count, hair_count = int((keep & (part == 0)).sum()), int((keep & (part == 1)).sum())
        tube = np.flatnonzero(keep & (part == 2))
        wanted = int(np.clip(clutter * shape_count - hair_count, 0, len(tube)))
        keep[tube[np.argsort(-hits[tube] @ up)[wanted:]]] = False
    hits, cells, part = hits[keep], cells[keep], part[keep]
    depth = (hits - frame.center) @ toward
    mesh_faces = _grid_mesh(cells, depth, grid, step)
    used, remap = np.unique(mesh_faces, return_inverse=True)
    if len(used) < 10:
        raise StatfitError(f"only {len(used)} scan points are visible from yaw {yaw_deg}, pitch {pitch_deg}")
    scan = hits[used] + rng.normal(scale=noise * frame.scale, size=(len(used), 1)) * toward
    to_scan = Similarity(SCAN_UNITS_PER_METRE[units] / model_units(vertices))
    if posed:
        rotation = Rotation.random(random_state=rng).as_matrix()
        offset = rng.uniform(-5, 5, size=3) * frame.scale * to_scan.scale
        to_scan = Similarity(to_scan.scale, rotation, offset - to_scan.scale * rotation @ frame.center)
    return RealisticScan(to_scan.apply(scan), remap.reshape(-1, 3), part[used] == 0, to_scan.apply(vertices), to_scan)
