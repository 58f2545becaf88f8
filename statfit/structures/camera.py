"""Pinhole camera in the OpenCV convention.

Camera axes: x right, y down, z forward (into the scene). Pixel (0, 0) is the top-left pixel and
covers [0, 1]² in pixel coordinates, so pixel centres lie at integer + 0.5; pixel (col, row) is
entry ``[row, col]`` of an (H, W) image.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from statfit.errors import StatfitError

_RIGID_TOL = 1e-6
CONVENTIONS = ("opencv", "opengl")
POSE_KEYS = ("world_to_camera", "camera_to_world")
# The most pixels a camera's image may have (8192²): a render of more (a splat render at 20000² asked
# for 4.8 GB a buffer) exhausts a workstation's memory before it could be written.
MAX_CAMERA_PIXELS = 1 << 26


def _matrix(value: Any, shape: tuple[int, int], name: str) -> np.ndarray:
    try:
        array = np.asarray(value.detach().cpu() if isinstance(value, torch.Tensor) else value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise StatfitError(f"camera {name} is not a numeric matrix: {exc}") from None
    if array.shape != shape:
        raise StatfitError(f"camera {name} must have shape {shape}, got {array.shape}")
    if not np.isfinite(array).all():
        raise StatfitError(f"camera {name} has non-finite entries")
    return array


def _rigid(pose: np.ndarray, name: str) -> np.ndarray:
    """``pose`` (4, 4), refused unless a rotation (orthonormal, det +1) and a translation."""
    rotation = pose[:3, :3]
    if (not np.allclose(pose[3], [0.0, 0.0, 0.0, 1.0], atol=_RIGID_TOL)
            or not np.allclose(rotation @ rotation.T, np.eye(3), atol=_RIGID_TOL) or np.linalg.det(rotation) < 0):
        raise StatfitError(f"camera {name} must be rigid: a rotation (orthonormal, det +1) and a translation, with "
                           "bottom row (0, 0, 0, 1)")
    return pose


@dataclass(frozen=True, eq=False)
class Camera:
    """Image size, intrinsics ``K`` (3, 3) and the rigid ``world_to_camera`` transform (4, 4).

    Accepts arrays or tensors; stores float64 CPU tensors (methods move them to the input's
    dtype and device). Raises :class:`StatfitError` for a non-positive size, a singular or
    non-pinhole ``K`` (bottom row must be (0, 0, 1)) or a non-rigid ``world_to_camera``.
    """

    width: int
    height: int
    K: torch.Tensor
    world_to_camera: torch.Tensor

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise StatfitError(f"camera {name} must be a positive integer, got {value!r}")
            object.__setattr__(self, name, int(value))
        if self.width * self.height > MAX_CAMERA_PIXELS:
            raise StatfitError(f"the camera's image of {self.width}×{self.height} pixels is larger than the "
                               f"{MAX_CAMERA_PIXELS:,} statfit renders")
        K = _matrix(self.K, (3, 3), "K")
        if not np.allclose(K[2], [0.0, 0.0, 1.0]):
            raise StatfitError(f"camera K must have bottom row (0, 0, 1), got {K[2].tolist()}")
        if np.linalg.matrix_rank(K) < 3:
            raise StatfitError(f"camera K is singular: {K.tolist()}")
        pose = _rigid(_matrix(self.world_to_camera, (4, 4), "world_to_camera"), "world_to_camera")
        object.__setattr__(self, "K", torch.as_tensor(K))
        object.__setattr__(self, "world_to_camera", torch.as_tensor(pose))

    @classmethod
    def look_at(cls, eye: Any, target: Any, up: Any, fov_deg: float, width: int, height: int) -> Camera:
        """Camera at ``eye`` looking at ``target`` with ``up`` (3,) towards the image top;
        ``fov_deg`` is the vertical field of view; square pixels, principal point at the image centre."""
        eye, target, up = (np.asarray(v, dtype=np.float64).reshape(3) for v in (eye, target, up))
        if not 0.0 < fov_deg < 180.0:
            raise StatfitError(f"camera field of view must be in (0, 180) degrees, got {fov_deg}")
        forward = target - eye
        if np.linalg.norm(forward) == 0.0:
            raise StatfitError("camera eye and target coincide")
        forward = forward / np.linalg.norm(forward)
        right = np.cross(forward, up)
        if np.linalg.norm(right) < 1e-9 * max(np.linalg.norm(up), 1e-300):
            raise StatfitError("camera up vector is parallel to the viewing direction")
        right = right / np.linalg.norm(right)
        down = np.cross(forward, right)
        rotation = np.stack([right, down, forward])
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = rotation, -rotation @ eye
        focal = 0.5 * height / np.tan(np.radians(fov_deg) / 2)
        K = np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
        return cls(width, height, K, pose)

    @property
    def rotation(self) -> torch.Tensor:
        """World-to-camera rotation (3, 3)."""
        return self.world_to_camera[:3, :3]

    @property
    def center(self) -> torch.Tensor:
        """Camera centre in world coordinates (3,)."""
        return -self.rotation.T @ self.world_to_camera[:3, 3]

    def to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """World points (N, 3) → camera coordinates (N, 3); differentiable."""
        pose = self.world_to_camera.to(points)
        return points @ pose[:3, :3].T + pose[:3, 3]

    def camera_to_pixels(self, points: torch.Tensor) -> torch.Tensor:
        """Camera-space points (N, 3) with z > 0 → pixel coordinates (N, 2) (x = column, y = row)."""
        K = self.K.to(points)
        return (points[:, :2] @ K[:2, :2].T) / points[:, 2:3] + K[:2, 2]

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World points (N, 3) → pixel coordinates (N, 2) and camera depth z (N,); differentiable."""
        local = self.to_camera(points)
        return self.camera_to_pixels(local), local[:, 2]

    def pixel_rays(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays through the pixel centres: origin (3,) and unit world directions (H, W, 3), float64."""
        rows, cols = torch.meshgrid(torch.arange(self.height, dtype=torch.float64) + 0.5,
                                    torch.arange(self.width, dtype=torch.float64) + 0.5, indexing="ij")
        pixels = torch.stack([cols, rows, torch.ones_like(rows)], dim=-1)
        directions = pixels @ torch.linalg.inv(self.K).T @ self.rotation
        return self.center, directions / directions.norm(dim=-1, keepdim=True)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description: width, height, K, world_to_camera (nested lists), convention."""
        return {"width": self.width, "height": self.height, "K": self.K.tolist(),
                "world_to_camera": self.world_to_camera.tolist(), "convention": "opencv"}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Camera:
        """Inverse of :meth:`to_dict`, and what other tools write: the pose as ``world_to_camera`` or
        its inverse ``camera_to_world`` (NeRF's and Blender's), in the ``convention`` 'opencv' (x right,
        y down, z forward) or 'opengl' (x right, y up, z towards the viewer: the camera looks down its
        −z); ``K`` is the pixel matrix either way. Raises :class:`StatfitError` on missing keys, both
        poses or another convention."""
        if not isinstance(data, dict):
            raise StatfitError(f"camera description must be a JSON object, got {type(data).__name__}")
        poses = [key for key in POSE_KEYS if key in data]
        missing = [key for key in ("width", "height", "K") if key not in data] + (
            [" or ".join(POSE_KEYS)] if not poses else [])
        if missing:
            raise StatfitError(f"camera description lacks {', '.join(missing)}")
        if len(poses) > 1:
            raise StatfitError("camera description has both world_to_camera and camera_to_world: give one")
        convention = data.get("convention", "opencv")
        if convention not in CONVENTIONS:
            raise StatfitError(f"camera convention must be 'opencv' or 'opengl', got {convention!r}")
        pose = _matrix(data[poses[0]], (4, 4), poses[0])
        if poses[0] == "camera_to_world":
            rotation = _rigid(pose, "camera_to_world")[:3, :3]
            pose = np.block([[rotation.T, -rotation.T @ pose[:3, 3:]], [pose[3:]]])
        if convention == "opengl":
            pose = np.diag([1.0, -1.0, -1.0, 1.0]) @ pose
        return cls(data["width"], data["height"], data["K"], pose)
