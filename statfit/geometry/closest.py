"""Closest points on a triangle mesh for many query points, vectorised in torch.

Candidates: the triangles around the ``k`` nearest mesh vertices of each query (scipy cKDTree);
each candidate is solved exactly (projection inside the triangle or the closest point on one of
its edges), and the nearest wins. With k ≥ 3 this finds the true closest triangle on meshes with
reasonably shaped triangles; the fits use k = 2, exact for > 95% of points near a head-sized mesh
(tests/test_geometry.py) at half the cost, and the rest land on a neighbouring triangle.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class SurfacePoints:
    """Closest surface points: triangle ids (M,), barycentrics (M, 3), distances (M,)."""

    triangle: torch.Tensor
    barycentric: torch.Tensor
    distance: torch.Tensor


def vertex_triangle_table(faces: np.ndarray, num_vertices: int) -> np.ndarray:
    """(N, D) triangles incident to each vertex, rows padded by repeating their first entry."""
    faces = np.asarray(faces, dtype=np.int64)
    vertex = faces.reshape(-1)
    triangle = np.repeat(np.arange(faces.shape[0]), 3)
    order = np.argsort(vertex, kind="stable")
    vertex, triangle = vertex[order], triangle[order]
    counts = np.bincount(vertex, minlength=num_vertices)
    width = max(int(counts.max()), 1)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(vertex.size) - starts[vertex]
    table = np.full((num_vertices, width), -1, dtype=np.int64)
    table[vertex, slot] = triangle
    first = np.where(table[:, :1] >= 0, table[:, :1], 0)
    return np.where(table >= 0, table, first)


def closest_on_triangles(points: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """Closest point on triangles (a, b, c) to ``points``, all (..., 3) broadcastable.

    Works on the six dot products of the point's offset and the edge vectors only: the squared
    distance of the point ``a + v·ab + w·ac`` is a quadratic in (v, w), minimised inside the triangle
    or on one of its edges. Returns barycentrics (..., 3) and squared distances (...).
    """
    ab, ac, ap = b - a, c - a, points - a
    dot = lambda x, y: (x * y).sum(-1)  # noqa: E731
    return _closest_in_triangle(dot(ap, ab), dot(ap, ac), dot(ap, ap), dot(ab, ab), dot(ab, ac), dot(ac, ac))


def _closest_in_triangle(d20: torch.Tensor, d21: torch.Tensor, dpp: torch.Tensor, d00: torch.Tensor,
                         d01: torch.Tensor, d11: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`closest_on_triangles` from the dot products (...) ap·ab, ap·ac, ap·ap of the point's
    offset ap to corner a with the edges ab, ac, and ab·ab, ab·ac, ac·ac, which depend on the
    triangle only (so a query computes them once per triangle, not once per candidate)."""
    tiny = torch.finfo(d20.dtype).tiny

    def sq_dist(v: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        return dpp - 2 * (v * d20 + w * d21) + v * v * d00 + 2 * v * w * d01 + w * w * d11

    denom = (d00 * d11 - d01 * d01).clamp_min(tiny)
    v = (d11 * d20 - d01 * d21) / denom
    w = (d00 * d21 - d01 * d20) / denom
    inside = (v >= 0) & (w >= 0) & (v + w <= 1)
    best = torch.where(inside, sq_dist(v, w), torch.inf)
    edges = (  # (v, w) on AB, AC and BC
        lambda t: (t, torch.zeros_like(t)),
        lambda t: (torch.zeros_like(t), t),
        lambda t: (1 - t, t),
    )
    params = (d20 / d00.clamp_min(tiny), d21 / d11.clamp_min(tiny),
              (d21 - d20 - d01 + d00) / (d11 - 2 * d01 + d00).clamp_min(tiny))
    for to_vw, t in zip(edges, params):
        ev, ew = to_vw(t.clamp(0, 1))
        dist = sq_dist(ev, ew)
        better = dist < best
        v, w = torch.where(better, ev, v), torch.where(better, ew, w)
        best = torch.where(better, dist, best)
    return torch.stack([1 - v - w, v, w], dim=-1), best.clamp_min(0)


def open_edges(faces: torch.Tensor) -> torch.Tensor:
    """(F, 3) bool: whether the edge opposite each triangle corner is on the mesh's open boundary
    (used by one triangle only)."""
    edges = torch.stack([faces[:, [1, 2]], faces[:, [2, 0]], faces[:, [0, 1]]], dim=1).sort(dim=-1).values
    keys = edges[..., 0] * (int(faces.max()) + 1) + edges[..., 1]   # one integer per undirected edge
    _, inverse, counts = torch.unique(keys.reshape(-1), return_inverse=True, return_counts=True)
    return (counts[inverse] == 1).view(-1, 3)


class ClosestPointQuery:
    """Closest points on a mesh of fixed topology whose vertices move between queries; ``open_edges``
    (F, 3) marks the topology's border edges (:func:`open_edges`)."""

    def __init__(self, faces: np.ndarray, num_vertices: int, k: int = 4, device: str | torch.device = "cpu"):
        self.k = k
        self.faces = torch.as_tensor(np.asarray(faces, dtype=np.int64), device=device)
        self.open_edges = open_edges(self.faces)
        self._ring = torch.as_tensor(vertex_triangle_table(faces, num_vertices), device=device)

    def __call__(self, vertices: torch.Tensor, points: torch.Tensor) -> SurfacePoints:
        """Closest points on the surface with ``vertices`` (N, 3) to ``points`` (M, 3)."""
        with torch.no_grad():
            tree = cKDTree(vertices.detach().cpu().double().numpy(), balanced_tree=False)   # built per query: 1.7x faster to build
            _, nearest = tree.query(points.detach().cpu().double().numpy(), k=self.k)
            nearest = torch.as_tensor(nearest.reshape(len(points), -1), device=points.device)
            candidates = self._ring[nearest].reshape(len(points), -1)      # (M, C)
            a, b, c = vertices[self.faces].unbind(dim=1)                   # (F, 3) each
            ab, ac = b - a, c - a
            # one plane per quantity (12, F), so that every product below runs over contiguous memory
            per_triangle = torch.cat([a.T, ab.T, ac.T, (ab * ab).sum(-1)[None], (ab * ac).sum(-1)[None],
                                      (ac * ac).sum(-1)[None]])
            gathered = per_triangle.index_select(1, candidates.reshape(-1)).view(12, *candidates.shape)   # (12, M, C)
            corner, edge_b, edge_c = gathered[0:3], gathered[3:6], gathered[6:9]                     # (3, M, C)
            offset = points.T[:, :, None] - corner
            dot = lambda x, y: x[0] * y[0] + x[1] * y[1] + x[2] * y[2]  # noqa: E731
            bary, sq = _closest_in_triangle(dot(offset, edge_b), dot(offset, edge_c), dot(offset, offset),
                                            *gathered[9:12])
            best = sq.argmin(dim=1)
            rows = torch.arange(len(points), device=points.device)
            triangle, bary = candidates[rows, best], bary[rows, best]
            surface = (corner[:, rows, best] + bary[:, 1] * edge_b[:, rows, best]
                       + bary[:, 2] * edge_c[:, rows, best]).T
            return SurfacePoints(triangle, bary, (surface - points).norm(dim=-1))
