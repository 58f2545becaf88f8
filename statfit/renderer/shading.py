"""Vertex normals and the normal-map renderer built on rasterize + antialias."""
from __future__ import annotations

from typing import Literal

import torch

from statfit.errors import StatfitError
from statfit.renderer.silhouette import MeshAdjacency, silhouette_crossings
from statfit.structures.camera import Camera
from statfit.renderer.raster import Fragments, interpolate_fragments, rasterize


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unit vertex normals (N, 3): area-weighted face normals summed at the vertices; differentiable.

    vertices: (N, 3); faces: (F, 3) long, counter-clockwise seen from the side the normals face.
    Returns a view of a (3, N) tensor.
    """
    index = faces.T.reshape(-1)                                       # (3F,) corner-major
    a, b, c = vertices.T.index_select(1, index).view(3, 3, -1).unbind(dim=1)   # (3, F) each
    face_normals = torch.linalg.cross(b - a, c - a, dim=0)             # length = twice the area
    summed = vertices.new_zeros(3, len(vertices)).index_add_(1, index, face_normals.repeat(1, 3))
    return (summed / (summed * summed).sum(dim=0).sqrt().clamp_min(torch.finfo(summed.dtype).tiny)).T


def render_normals(vertices: torch.Tensor, faces: torch.Tensor, camera: Camera, *,
                   adjacency: MeshAdjacency | None = None, space: Literal["camera", "world"] = "camera"
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Antialiased normal map (H, W, 3) and coverage mask (H, W) of a mesh; both differentiable
    w.r.t. ``vertices`` (N, 3), including silhouette gradients.

    faces: (F, 3) long; adjacency: ``MeshAdjacency.from_faces(faces)``, pass it to reuse it across
    calls; space: see :func:`normal_image`. Background normals are zero and blend with the
    surface's at the outline.
    """
    fragments = rasterize(vertices, faces, camera)
    adjacency = MeshAdjacency.from_faces(faces) if adjacency is None else adjacency
    normals = normal_image(vertices, faces, fragments, camera, space=space)
    crossings = silhouette_crossings(fragments, faces, adjacency)
    return crossings.blend(normals), crossings.blend(fragments.coverage(normals.dtype))[..., 0]


def normal_image(vertices: torch.Tensor, faces: torch.Tensor, fragments: Fragments, camera: Camera, *,
                 space: Literal["camera", "world"] = "camera") -> torch.Tensor:
    """Unit normals (H, W, 3) interpolated from the vertex normals and renormalised per pixel, zero
    on the background (not antialiased); in camera (OpenCV axes) or world coordinates."""
    return fragments.to_image(fragment_normals(vertices, faces, fragments, camera, space=space))


def fragment_normals(vertices: torch.Tensor, faces: torch.Tensor, fragments: Fragments, camera: Camera, *,
                     space: Literal["camera", "world"] = "camera") -> torch.Tensor:
    """The unit normals of :func:`normal_image` at the covered pixels only, (3, M) in
    ``fragments.pixel`` order; differentiable w.r.t. ``vertices``."""
    if space not in ("camera", "world"):
        raise StatfitError(f"normal space must be 'camera' or 'world', got {space!r}")
    normals = vertex_normals(vertices, faces).T                       # (3, N)
    if space == "camera":
        normals = camera.rotation.to(normals) @ normals
    return interpolate_fragments(normals.T, faces, fragments, normalize=True)
