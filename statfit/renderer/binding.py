"""Surfels bound to a mesh's triangles, so that moving the vertices moves, turns and stretches them.

Each splat has a triangle and fixed barycentric coordinates; its centre is that point of the
triangle, its tangents are the triangle's frame (first edge, then normal × edge) turned by a
free in-plane angle, and its scales are free factors times the triangle's size √area. Colours
(sigmoid of free logits) and opacities (sigmoid) are free. There is no offset along the normal:
the geometry is the vertices' alone (a free offset lets splats float off a wrong surface and
take the images' gradient away from the vertices).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from statfit.errors import StatfitError
from statfit.renderer.surfels import Surfels

# Barycentric patterns of splats on a triangle, by splats per triangle.
PATTERNS = {
    1: ((1 / 3, 1 / 3, 1 / 3),),
    3: ((2 / 3, 1 / 6, 1 / 6), (1 / 6, 2 / 3, 1 / 6), (1 / 6, 1 / 6, 2 / 3)),
    4: ((1 / 3, 1 / 3, 1 / 3), (2 / 3, 1 / 6, 1 / 6), (1 / 6, 2 / 3, 1 / 6), (1 / 6, 1 / 6, 2 / 3)),
}
# Starting σ per splat, in units of √(triangle area / splats per triangle): neighbouring splats
# overlap enough that the surface starts closed.
START_SCALE = 0.6
START_OPACITY = 0.9
START_COLOUR = 0.5


@dataclass
class MeshSplats:
    """P splats on the triangles of a mesh with faces (F, 3).

    triangle (P,) long, barycentric (P, 3): where each splat sits (fixed); angle (P,): in-plane
    turn from the triangle's frame; log_scale (P, 2): σ / √area; colour_logit (P, C),
    opacity_logit (P,). The free tensors are leaves that require grad (:meth:`parameters`)."""

    faces: torch.Tensor
    triangle: torch.Tensor
    barycentric: torch.Tensor
    angle: torch.Tensor
    log_scale: torch.Tensor
    colour_logit: torch.Tensor
    opacity_logit: torch.Tensor

    @classmethod
    def on(cls, faces: torch.Tensor, per_triangle: int = 1, channels: int = 3, dtype: torch.dtype = torch.float32
           ) -> MeshSplats:
        """``per_triangle`` splats (1, 3 or 4) on every triangle of ``faces`` (F, 3) long, grey, σ
        :data:`START_SCALE` × √(area / per_triangle)."""
        if per_triangle not in PATTERNS:
            raise StatfitError(f"splats per triangle must be one of {', '.join(map(str, PATTERNS))}, got "
                               f"{per_triangle}")
        pattern = torch.tensor(PATTERNS[per_triangle], dtype=dtype, device=faces.device)
        count = len(faces) * per_triangle
        triangle = torch.arange(len(faces), device=faces.device).repeat_interleave(per_triangle)
        barycentric = pattern.repeat(len(faces), 1)
        scale = float(np.log(START_SCALE / np.sqrt(per_triangle)))

        def leaf(value: torch.Tensor) -> torch.Tensor:
            return value.to(dtype).requires_grad_(True)

        logit = lambda p: float(np.log(p / (1 - p)))  # noqa: E731
        zeros = torch.zeros(count, device=faces.device)
        return cls(faces, triangle, barycentric, leaf(zeros.clone()), leaf(torch.full((count, 2), scale,
                                                                                      device=faces.device)),
                   leaf(torch.full((count, channels), logit(START_COLOUR), device=faces.device)),
                   leaf(torch.full((count,), logit(START_OPACITY), device=faces.device)))

    def __len__(self) -> int:
        return len(self.triangle)

    def parameters(self) -> dict[str, torch.Tensor]:
        """The free tensors by name."""
        return {"angle": self.angle, "log_scale": self.log_scale, "colour_logit": self.colour_logit,
                "opacity_logit": self.opacity_logit}

    def surfels(self, vertices: torch.Tensor) -> Surfels:
        """The splats on the mesh with ``vertices`` (N, 3); differentiable w.r.t. the vertices and
        every free tensor."""
        corners = vertices.index_select(0, self.faces.index_select(0, self.triangle).reshape(-1)).view(-1, 3, 3)
        centres = (self.barycentric[:, :, None] * corners).sum(dim=1)
        edge_1 = corners[:, 1] - corners[:, 0]
        cross = torch.linalg.cross(edge_1, corners[:, 2] - corners[:, 0], dim=1)
        twice_area = cross.norm(dim=1, keepdim=True).clamp_min(torch.finfo(vertices.dtype).tiny)
        normal = cross / twice_area
        first = edge_1 / edge_1.norm(dim=1, keepdim=True).clamp_min(torch.finfo(vertices.dtype).tiny)
        second = torch.linalg.cross(normal, first, dim=1)
        cos, sin = torch.cos(self.angle)[:, None], torch.sin(self.angle)[:, None]
        tangent_u = cos * first + sin * second
        tangent_v = cos * second - sin * first
        size = torch.sqrt(0.5 * twice_area)
        return Surfels(centres, tangent_u, tangent_v, torch.exp(self.log_scale) * size,
                       torch.sigmoid(self.colour_logit), torch.sigmoid(self.opacity_logit))
