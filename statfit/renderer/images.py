"""Plain pictures of a mesh, with no gradients needed: the ground-truth images that synthetic data
and previews are made of (a normal map without antialiasing, a shaded photograph)."""
from __future__ import annotations

from typing import Literal

import numpy as np
import torch

from statfit.renderer.raster import interpolate_fragments, rasterize
from statfit.renderer.shading import fragment_normals, normal_image
from statfit.structures.camera import Camera

LIGHT = np.array([-0.4, 0.5, 0.75]) / np.linalg.norm([-0.4, 0.5, 0.75])  # towards the light, model frame
AMBIENT = 0.35
SUPERSAMPLE = 2


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
