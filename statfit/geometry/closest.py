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

from statfit.errors import DivergenceError
from statfit.structures.kdtree import kd_tree


@dataclass(frozen=True)
class SurfacePoints:
    """Closest surface points: triangle ids (M,), barycentrics (M, 3), distances (M,)."""

    triangle: torch.Tensor
    barycentric: torch.Tensor
    distance: torch.Tensor


def vertex_triangle_lists(faces: np.ndarray, num_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The triangles incident to each vertex, in one flat list: triangles (T,), each vertex's first
    entry (N,) and its count (N,), in face order per vertex. A vertex of no triangle lists
    triangle 0 (so every vertex has at least one candidate)."""
    faces = np.asarray(faces, dtype=np.int64)
    counts = np.bincount(faces.reshape(-1), minlength=num_vertices)
    lonely = np.flatnonzero(counts == 0)
    vertex = np.concatenate([faces.reshape(-1), lonely])
    triangle = np.concatenate([np.repeat(np.arange(faces.shape[0]), 3), np.zeros(len(lonely), dtype=np.int64)])
    counts = np.maximum(counts, 1)
    return triangle[np.argsort(vertex, kind="stable")], np.cumsum(counts) - counts, counts


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
    v, w, sq = _closest_in_triangle_vw(d20, d21, dpp, d00, d01, d11)
    return torch.stack([1 - v - w, v, w], dim=-1), sq


def _closest_in_triangle_vw(d20: torch.Tensor, d21: torch.Tensor, dpp: torch.Tensor, d00: torch.Tensor,
                            d01: torch.Tensor, d11: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_closest_in_triangle` as (v, w, squared distance), the closest point ``a + v·ab + w·ac``.

    The four candidates (the projection if inside, the closest points of edges AB, AC, BC) are
    evaluated as one stack and the first nearest wins: the same values as trying them in turn, in a
    few large torch ops instead of four rounds of small ones (each op a kernel launch on a GPU)."""
    tiny = torch.finfo(d20.dtype).tiny
    denom = (d00 * d11 - d01 * d01).clamp_min(tiny)
    v = (d11 * d20 - d01 * d21) / denom
    w = (d00 * d21 - d01 * d20) / denom
    outside = (v < 0) | (w < 0) | (v + w > 1)
    t = torch.stack([d20 / d00.clamp_min(tiny), d21 / d11.clamp_min(tiny),
                     (d21 - d20 - d01 + d00) / (d11 - 2 * d01 + d00).clamp_min(tiny)]).clamp_(0, 1)
    t_ab, t_ac, t_bc = t.unbind(0)
    zero = torch.zeros_like(v)
    vs = torch.stack([v, t_ab, zero, 1 - t_bc])        # (v, w) inside, then on AB, AC and BC
    ws = torch.stack([w, zero, t_ac, t_bc])
    sq = dpp - 2 * (vs * d20 + ws * d21) + vs * vs * d00 + 2 * vs * ws * d01 + ws * ws * d11   # (4, ...)
    sq[0].masked_fill_(outside, torch.inf)
    sq.nan_to_num_(nan=torch.inf, posinf=torch.inf)
    # The first nearest, as trying them in turn (``min`` over a leading dimension: ``argmin`` there
    # is ~7x slower on a CPU, and the minimum's value comes with its index).
    sq, best = sq.min(dim=0, keepdim=True)
    return vs.gather(0, best)[0], ws.gather(0, best)[0], sq[0].clamp_min(0)


def open_edges(faces: torch.Tensor) -> torch.Tensor:
    """(F, 3) bool: whether the edge opposite each triangle corner is on the mesh's open boundary
    (used by one triangle only)."""
    edges = torch.stack([faces[:, [1, 2]], faces[:, [2, 0]], faces[:, [0, 1]]], dim=1).sort(dim=-1).values
    keys = edges[..., 0] * (int(faces.max()) + 1) + edges[..., 1]   # one integer per undirected edge
    _, inverse, counts = torch.unique(keys.reshape(-1), return_inverse=True, return_counts=True)
    return (counts[inverse] == 1).view(-1, 3)


def border_vertices(opposite_open: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The vertices on a mesh's open boundary, sorted, from ``opposite_open`` (F, 3) bool, whether
    the edge opposite each corner of ``faces`` (F, 3) is open (:func:`open_edges`)."""
    return np.unique(np.concatenate([faces[opposite_open[:, i]][:, [(i + 1) % 3, (i + 2) % 3]].reshape(-1)
                                     for i in range(3)]))


class ClosestPointQuery:
    """Closest points on a mesh of fixed topology whose vertices move between queries; ``open_edges``
    (F, 3) marks the topology's border edges (:func:`open_edges`)."""

    def __init__(self, faces: np.ndarray, num_vertices: int, k: int = 4, device: str | torch.device = "cpu"):
        self.k, self.num_vertices = min(k, num_vertices), num_vertices     # a tiny mesh: all its vertices
        self.faces = torch.as_tensor(np.asarray(faces, dtype=np.int64), device=device)
        self.open_edges = open_edges(self.faces)
        # on the host: the candidates are listed where the KD-tree query runs
        self._ring, self._ring_first, self._ring_count = vertex_triangle_lists(faces, num_vertices)
        self._faces_flat = self.faces.reshape(-1)
        self._stacked: torch.Tensor | None = None   # B copies of the faces (:meth:`stacked_faces`)

    def _candidates(self, nearest: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The triangles around each point's nearest vertices ``nearest`` (M, k), one flat list (L,)
        grouped by point (no padding: a vertex of few triangles costs only those), and each one's
        point (L,). On the host, where the tree query ran, so the device never waits for a count."""
        nearest = nearest.reshape(-1)
        sizes = self._ring_count[nearest]
        group = np.repeat(np.arange(len(nearest)), sizes)
        within = np.arange(len(group)) - (np.cumsum(sizes) - sizes)[group]
        return self._ring[self._ring_first[nearest][group] + within], group // self.k

    def __call__(self, vertices: torch.Tensor, points: torch.Tensor, host_points: np.ndarray | None = None
                 ) -> SurfacePoints:
        """Closest points on the surface with ``vertices`` (N, 3) to ``points`` (M, 3);
        ``host_points``: the points as a float64 NumPy array, if the caller keeps one (a scan
        queried again and again: no copy each time). Raises DivergenceError for non-finite vertices."""
        with torch.no_grad():
            vertices = vertices.detach() if vertices.requires_grad else vertices
            if host_points is None:
                host_points = (points.detach() if points.requires_grad else points).cpu().double().numpy()
            candidates, owner = self._host_candidates(vertices.cpu().double().numpy(), host_points)
            return self._solve(vertices, self._faces_flat, points, *(torch.as_tensor(a, device=points.device)
                                                                     for a in (candidates, owner)))

    def many(self, vertices: torch.Tensor, points: torch.Tensor, host_points: np.ndarray) -> SurfacePoints:
        """Closest points for B meshes of this topology at once: ``vertices`` (B, N, 3), ``points``
        (B, M, 3) (``host_points`` the same as float64 NumPy), each fit's points on its own mesh.
        Triangle ids (B·M,) count the B meshes' triangles one after another (mesh b's: b·F + t);
        barycentrics (B·M, 3), distances (B·M,). One read of the vertices from the device; a tree
        per mesh on the host; the candidates of all B solved together."""
        with torch.no_grad():
            vertices = vertices.detach() if vertices.requires_grad else vertices
            fits, count = points.shape[:2]
            host = vertices.cpu().double().numpy()
            triangles = len(self.faces)
            listed = [self._host_candidates(host[b], host_points[b]) for b in range(fits)]
            candidates = np.concatenate([c + b * triangles for b, (c, _) in enumerate(listed)])
            owner = np.concatenate([o + b * count for b, (_, o) in enumerate(listed)])
            return self._solve(vertices.reshape(-1, 3), self.stacked_faces(fits).view(-1), points.reshape(-1, 3),
                               *(torch.as_tensor(a, device=points.device) for a in (candidates, owner)))

    def stacked_faces(self, fits: int) -> torch.Tensor:
        """(B·F, 3): the faces of ``fits`` meshes of this topology stacked (B·N vertices), mesh b's
        vertex v at row b·N + v; the last B's kept."""
        if self._stacked is None or len(self._stacked) != fits * len(self.faces):
            shift = torch.arange(fits, device=self.faces.device).mul_(self.num_vertices)
            self._stacked = (self.faces[None] + shift[:, None, None]).reshape(-1, 3)
        return self._stacked

    def _host_candidates(self, host: np.ndarray, host_points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The candidate triangles of each point and each one's point, on the host (a KD-tree of
        the vertices ``host`` (N, 3), float64)."""
        if not np.isfinite(host).all():
            raise DivergenceError("the fit diverged: vertices are not finite (step size too large?)")
        tree = kd_tree(host, balanced_tree=False)   # built per query: 1.7x faster to build
        _, nearest = tree.query(host_points, k=self.k)
        return self._candidates(nearest)

    @staticmethod
    def _solve(vertices: torch.Tensor, faces_flat: torch.Tensor, points: torch.Tensor, candidates: torch.Tensor,
               owner: torch.Tensor) -> SurfacePoints:
        """Each point's nearest among its ``candidates`` (L,) triangles (rows of ``faces_flat``
        (3F,) viewed (F, 3)) of ``vertices`` (N, 3); ``owner`` (L,): each candidate's point."""
        count, total = len(points), len(candidates)
        lane = torch.arange(total, device=points.device)
        corners = vertices.index_select(0, faces_flat).view(-1, 3, 3)                # (F, corner, xyz)
        ab, ac = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
        products = torch.stack([(ab * ab).sum(-1), (ab * ac).sum(-1), (ac * ac).sum(-1)])   # (3, F)
        # one plane per quantity (12, F), so that every product below runs over contiguous memory
        per_triangle = torch.cat([corners[:, 0].T, ab.T, ac.T, products])
        gathered = per_triangle.index_select(1, candidates)                               # (12, L)
        offset = points.T.index_select(1, owner) - gathered[0:3]                         # (3, L)
        # ap·ab, ap·ac, ap·ap at once: (edge b, edge c, offset) · offset, summed over xyz in order
        dots = (torch.cat([gathered[3:9].view(2, 3, -1), offset[None]]) * offset).sum(1)
        v, w, sq = _closest_in_triangle_vw(*dots, *gathered[9:12])
        # Per point, the first of its nearest candidates (as argmin over a row of them).
        nearest_sq = sq.new_full((count,), torch.inf).scatter_reduce_(0, owner, sq, "amin")
        first = torch.where(sq == nearest_sq.index_select(0, owner), lane, total)
        best = lane.new_full((count,), total).scatter_reduce_(0, owner, first, "amin")    # (M,)
        triangle = candidates.index_select(0, best)
        # the winner's corner and edges (9 planes) and its (v, w), in one gather: (11, M)
        picked = torch.cat([gathered[:9], v[None], w[None]]).index_select(1, best)
        corner, edge_b, edge_c, (v, w) = picked[0:3], picked[3:6], picked[6:9], picked[9:11]
        bary = torch.stack([1 - v - w, v, w], dim=-1)
        surface = (corner + v * edge_b + w * edge_c).T
        return SurfacePoints(triangle, bary, (surface - points).norm(dim=-1))
