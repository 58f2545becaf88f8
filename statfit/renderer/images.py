"""Plain pictures of a mesh, with no gradients needed: the ground-truth images that synthetic data
and previews are made of (a normal map without antialiasing, a shaded photograph, a per-vertex field
in colour, a shaded mesh with scan points over it) and the cameras previews look from."""
from __future__ import annotations

from typing import Literal

import numpy as np
import torch

from statfit.renderer.raster import interpolate, interpolate_fragments, rasterize
from statfit.renderer.shading import fragment_normals, normal_image
from statfit.structures.camera import Camera

LIGHT = np.array([-0.4, 0.5, 0.75]) / np.linalg.norm([-0.4, 0.5, 0.75])  # towards the light, model frame
AMBIENT = 0.35
SUPERSAMPLE = 2
FOV_DEG, FILL = 30.0, 0.9   # a preview's front camera: its field of view, and the share of it the mesh fills
FAR_SHARE = 0.05            # scan points this share of the fit's RMS radius off its surface are drawn red


def render_target(vertices: np.ndarray, faces: np.ndarray, camera: Camera,
                  space: Literal["world", "camera"] = "world") -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (H, W, 3) float32, in world or camera (OpenCV) axes, and the coverage mask
    (H, W) bool of a mesh: a normal map without antialiasing (every foreground pixel holds one
    surface's normal)."""
    points = torch.as_tensor(vertices, dtype=torch.float64)
    face_ids = torch.as_tensor(faces, dtype=torch.long)
    fragments = rasterize(points, face_ids, camera)
    normals = normal_image(points, face_ids, fragments, camera, space=space)
    return normals.numpy().astype(np.float32), (fragments.triangle >= 0).numpy()


def photograph(vertices: np.ndarray, faces: np.ndarray, albedo: np.ndarray, camera: Camera
               ) -> tuple[np.ndarray, np.ndarray]:
    """The mesh (N, 3), faces (F, 3), per-vertex ``albedo`` (N, 3) seen by ``camera``: colour
    (H, W, 3) over black and alpha (H, W), float32, antialiased by :data:`SUPERSAMPLE`²."""
    K = camera.K.clone()
    K[:2] *= SUPERSAMPLE
    fine = Camera(camera.width * SUPERSAMPLE, camera.height * SUPERSAMPLE, K, camera.world_to_camera)
    points = torch.as_tensor(vertices, dtype=torch.float64)
    face_ids = torch.as_tensor(faces, dtype=torch.long)
    fragments = rasterize(points, face_ids, fine)
    normals = fragment_normals(points, face_ids, fragments, fine, space="world")            # (3, M)
    light = torch.as_tensor(LIGHT, dtype=torch.float64)
    shade = AMBIENT + (1.0 - AMBIENT) * (light @ normals).clamp_min(0.0)
    colour = interpolate_fragments(torch.as_tensor(albedo, dtype=torch.float64), face_ids, fragments) * shade
    image = torch.cat([fragments.to_image(colour), fragments.coverage(torch.float64)], dim=-1).numpy()
    blocks = image.reshape(camera.height, SUPERSAMPLE, camera.width, SUPERSAMPLE, 4).mean(axis=(1, 3))
    return blocks[..., :3].astype(np.float32), blocks[..., 3].astype(np.float32)


def normals_to_rgb(normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Camera-space (OpenCV) unit normals (H, W, 3) → RGB in the usual look of normal maps
    (OpenGL axes: +x red, +y up green, +z towards the viewer blue); background white."""
    rgb = (normals * np.array([1.0, -1.0, -1.0]) + 1.0) / 2.0
    return np.where(mask[..., None], np.clip(rgb, 0.0, 1.0), 1.0)


def front_camera(vertices: np.ndarray, turn: np.ndarray, size: int) -> Camera:
    """A square camera (``size`` pixels) facing the model's front (+z, +y up in the model's frame)
    in the frame that ``turn`` (3, 3: model → data, scale included) puts the model in, framing
    ``vertices`` (N, 3)."""
    toward, up = turn[:, 2] / np.linalg.norm(turn[:, 2]), turn[:, 1] / np.linalg.norm(turn[:, 1])
    centre = vertices.mean(axis=0)
    radius = float(np.linalg.norm(vertices - centre, axis=1).max())
    distance = radius / np.sin(np.radians(FOV_DEG) / 2 * FILL)
    return Camera.look_at(centre + distance * toward, centre, up, FOV_DEG, size, size)


def turned_camera(camera: Camera, vertices: np.ndarray, degrees: float) -> Camera:
    """``camera`` turned by ``degrees`` about its own vertical axis through the mesh's centroid
    (``vertices`` (N, 3))."""
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


def field_top(values: np.ndarray) -> float:
    """The top of a per-vertex field's colour scale (its bottom is 0): the 99th percentile of its
    finite ``values``, so that a few outliers do not wash the rest out (1 without finite values)."""
    finite = values[np.isfinite(values)]
    return max(float(np.percentile(finite, 99)) if finite.size else 1.0, 1e-12)


def mesh_with_points(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, distance: np.ndarray,
                     camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """RGB (H, W, 3) in [0, 1] and what it shows (H, W) bool: the mesh (N, 3)/(F, 3) shaded by a
    headlight on white, as ``camera`` sees it, with the points (M, 3) it does not hide drawn over
    it, green on its surface to red ``FAR_SHARE`` of its RMS radius off (``distance`` (M,))."""
    corners = torch.as_tensor(vertices, dtype=torch.float64)
    fragments = rasterize(corners, torch.as_tensor(faces, dtype=torch.long), camera)
    normals = normal_image(corners, torch.as_tensor(faces, dtype=torch.long), fragments, camera).numpy()
    covered = fragments.triangle.numpy() >= 0
    shade = 0.25 + 0.65 * np.clip(-normals[..., 2], 0.0, 1.0)
    image = np.where(covered[..., None], shade[..., None] * np.array([0.85, 0.87, 0.95]), 1.0)
    pixels, depth = (value.numpy() for value in camera.project(torch.as_tensor(points, dtype=torch.float64)))
    column, line = np.floor(pixels[:, 0]).astype(np.int64), np.floor(pixels[:, 1]).astype(np.int64)
    inside = (column >= 0) & (column < camera.width) & (line >= 0) & (line < camera.height) & (depth > 0)
    surface = np.full(len(points), np.inf)
    surface[inside] = fragments.depth.numpy()[line[inside], column[inside]]
    radius = float(np.sqrt(((vertices - vertices.mean(axis=0)) ** 2).sum(axis=1).mean()))
    shown = np.flatnonzero(inside & (depth <= surface + 0.02 * radius))
    shown = shown[np.argsort(-depth[shown])]        # nearer points drawn last, over farther ones
    far = np.clip(distance[shown] / (FAR_SHARE * radius), 0.0, 1.0)[:, None]
    image[line[shown], column[shown]] = (1.0 - far) * np.array([0.1, 0.7, 0.2]) + far * np.array([0.9, 0.1, 0.1])
    covered[line[shown], column[shown]] = True
    return image, covered


def cropped(image: np.ndarray, keep: np.ndarray, margin: int = 4) -> np.ndarray:
    """``image`` (H, W, C) cut to the bounding box of ``keep`` (H, W) bool, plus ``margin`` pixels."""
    if not keep.any():
        return image
    rows, columns = np.flatnonzero(keep.any(axis=1)), np.flatnonzero(keep.any(axis=0))
    return image[max(rows[0] - margin, 0):rows[-1] + margin + 1, max(columns[0] - margin, 0):columns[-1] + margin + 1]
