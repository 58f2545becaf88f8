"""The pieces of :class:`statfit.renderer.steady.SteadyRenderer` with gradients: per-pixel normals and
silhouette crossing weights with hand-written backward passes, the view it returns and its blends,
vertex normals and silhouette flags; the walk from a pixel pair to its silhouette edge; gathers of
integer tables by columns; the copies of a mesh that one renderer draws for many views.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from statfit.renderer.silhouette import _EPS, MeshAdjacency

UNCOVERED_COLUMNS = 64      # the columns that blends into uncovered pixels write (and are dropped)


class _PixelNormals(torch.autograd.Function):
    """Perspective-correct unit normals (3, M) at pixel centres: Σ_k e_k n_k / z_k, normalised,
    where e_k are the edge functions at the pixel centre (the barycentrics × twice the signed
    area, so ``sign`` (M,) = the area's sign makes it the same for either winding).

    The sum is affine in the pixel centre within a triangle, so it is set up per triangle, as
    A + q_x B + q_y C with q the pixel centre less the triangle's first corner (A, B, C: (3,) each),
    and each pixel gathers 9 numbers instead of its three corners' 18.

    data: (6, N) screen x, y, depth, normal x, y, z per vertex; face: (M,) the pixels' triangles
    into the triangles (F+1) whose corner-major vertex indices are ``corners`` (3(F+1),) (the last
    triangle: none; it gets no gradient); offset: (2, M) each pixel centre less its triangle's
    first corner (no gradient); spread_face: (M,) ``face`` with the pixels of triangle F (the dump
    slots, whose gradients are zero) spread over the real triangles, the backward's scatter index.
    Hand-written backward: the pixels' gradients summed per triangle (9 numbers), then per vertex."""

    @staticmethod
    def forward(ctx, data, face, corners, offset, sign, spread_face):
        at = data.index_select(1, corners).view(6, 3, -1)                               # (6, 3, F+1)
        rel = at[:2] - at[:2, :1]                                                       # x, y from corner 0
        rel_j, rel_k = rel.roll(-1, 1), rel.roll(-2, 1)                                 # corners k+1, k+2
        # e_k(q) = a_k + q_x (y_j − y_k) − q_y (x_j − x_k): terms a, x_j − x_k, y_j − y_k (3, 3, F+1)
        terms = torch.cat([(rel_j[0] * rel_k[1] - rel_k[0] * rel_j[1])[None], rel_j - rel_k])
        w = at[3:] / at[2]                                                              # n_k / z_k (3, 3, F+1)
        planes = _corner_sum(terms[:, None], w[None], 2)                                 # (3 terms, 3, F+1)
        per_pixel = planes.view(9, -1).index_select(1, face).view(3, 3, -1)             # (3 terms, 3, M)
        summed = torch.addcmul(per_pixel[0], per_pixel[2], offset[0]).addcmul_(per_pixel[1], offset[1], value=-1)
        scale = (summed * summed).sum(dim=0).clamp_min(torch.finfo(summed.dtype).tiny).rsqrt() * sign
        normals = summed * scale
        ctx.save_for_backward(at, rel_j, rel_k, terms, w, normals, scale, spread_face, corners, offset)
        ctx.vertices = data.shape[1]
        return normals

    @staticmethod
    def backward(ctx, grad):
        at, rel_j, rel_k, terms, w, normals, scale, spread_face, corners, offset = ctx.saved_tensors
        along = scale * (grad - normals * (normals * grad).sum(dim=0))                 # d/d summed (3, M)
        per_pixel = torch.cat([along, along * offset[1], along * offset[0]])            # d/d planes (9, M)
        per_pixel[3:6].neg_()
        # The dump slots' zeros go to distinct triangles: no triangle gathers thousands of writes.
        planes = per_pixel.new_zeros(9, w.shape[2]).index_add_(1, spread_face, per_pixel).view(3, 3, -1)
        grad_w = _corner_sum(planes[:, :, None], terms[:, None], dim=0)                # (3, 3, F+1)
        grad_a, grad_d = _corner_sum(planes[:, :, None], w[None]).split([1, 2])       # (1 | 2, 3, F+1)
        # a = x_j y_k − x_k y_j; d = rel_j − rel_k; perp(v) = (v_y, −v_x).
        grad_j = torch.addcmul(grad_d, grad_a, _perp(rel_k))
        minus_grad_k = torch.addcmul(grad_d, grad_a, _perp(rel_j))
        grads = torch.empty(6, *w.shape[1:], dtype=w.dtype, device=w.device)
        torch.sub(grad_j.roll(1, 1), minus_grad_k.roll(2, 1), out=grads[:2])          # d/d rel (2, 3, F+1)
        torch.sum(grad_w * w, dim=0, out=grads[2]).div_(at[2]).neg_()                  # d/d depth
        torch.div(grad_w, at[2], out=grads[3:])                                         # d/d normal
        # Triangle F (vertex 0 thrice) adds zeros (no pixel's gradient reaches it), so all rows are
        # added as they lie: no copy of the others'.
        grad_data = grads.new_zeros(6, ctx.vertices).index_add_(1, corners, grads.view(6, -1))
        return grad_data, None, None, None, None, None


def _corner_sum(a: torch.Tensor, b: torch.Tensor, dim: int = 1) -> torch.Tensor:
    """Σ_k a_k b_k over a size-3 axis ``dim`` of the broadcast a · b (the axis dropped), as three
    products added in order (the bits of ``(a * b).sum(dim)``, without making that product, 3× the
    result's size; not ``addcmul``, which rounds otherwise)."""
    a, b = a.unbind(dim), b.unbind(dim)
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _columns(table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``table.index_select(1, index)`` for a table (C, L) of integers: as a ``gather``, which a CPU
    runs ~3× faster for them (its ``index_select`` along columns of integers is a slow path)."""
    return table.gather(1, index.expand(len(table), -1))


def _perp(v: torch.Tensor) -> torch.Tensor:
    """(v_y, −v_x) of v (2, ...): a new tensor (no constant to move to the device every call)."""
    out = v.flip(0)
    out[1].neg_()
    return out


class _CrossingWeights(torch.autograd.Function):
    """Blend weights ``|0.5 − d|`` (K,) of silhouette crossings, d ∈ [0, 1] where the edge between
    the vertices ``ends`` (2K,) crosses the segment from the pixel centre (K, 2) to its neighbour
    (along x where ``horizontal``, else y; ``direction`` ±1); and whether d < 0.5 (no gradient).
    As ``silhouette_crossings``; slots without a crossing (``hit`` false) weigh 0.
    Hand-written backward."""

    @staticmethod
    def forward(ctx, screen, ends, centre, horizontal, direction, hit):
        rel = screen.index_select(0, ends).view(-1, 2, 2) - centre[:, None]           # (K, 2 ends, 2)
        frame = torch.where(horizontal[:, None, None], rel, rel.flip(2))               # along, across
        (aj, bj), (ak, bk) = frame.unbind(1)[0].unbind(1), frame.unbind(1)[1].unbind(1)
        span = torch.where(hit, bk - bj, 1.0)
        raw = direction * (aj * bk - ak * bj) / span
        crossing = raw.clamp(0.0, 1.0)
        ctx.save_for_backward(ends, horizontal, frame, span,
                              direction * ((raw >= 0) & (raw <= 1) & hit) * torch.sign(crossing - 0.5))
        ctx.vertices = screen.shape[0]
        ctx.mark_non_differentiable(crossing)
        return torch.where(hit, 0.5 - crossing, 0.0).abs(), crossing < 0.5

    @staticmethod
    def backward(ctx, grad, _):
        ends, horizontal, frame, span, factor = ctx.saved_tensors
        q = grad * factor / span                                                        # d/d(aj bk − ak bj)
        (aj, bj), (ak, bk) = frame.unbind(1)[0].unbind(1), frame.unbind(1)[1].unbind(1)
        r = q * (aj - ak) / span
        # d/d(along, across) of the ends j, k: [q, r] ⊗ [bk, −bj]
        grads = torch.stack([bk, -bj], dim=1)[:, :, None] * torch.stack([q, r], dim=1)[:, None, :]
        grads = torch.where(horizontal[:, None, None], grads, grads.flip(2))
        grad_screen = grads.new_zeros(ctx.vertices, 2).index_add_(0, ends, grads.view(-1, 2))
        return grad_screen, None, None, None, None, None


def crossing_blends(screen: torch.Tensor, pairs: tuple[torch.Tensor, ...], edge_ends: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Blend targets, sources (K,) and differentiable weights of the silhouette ``pairs``
    (:class:`Visibility`) at the vertices' pixel positions ``screen`` (V, 2); edge_ends: (3(F+1), 2)
    the endpoints of edge e of triangle t at row 3t + e. Slots without a crossing weigh 0 and blend
    real pixels (a masked slot its own pixel with itself), so no one pixel gathers their writes."""
    inner, outer, axis, direction, centre, triangle, edge, hit = pairs
    with torch.no_grad():
        ends = edge_ends.index_select(0, triangle * 3 + edge)                           # (K, 2)
    weight, near_inner = _CrossingWeights.apply(screen, ends.view(-1), centre.T, axis == 0, direction, hit)
    with torch.no_grad():
        target = torch.where(near_inner, inner, outer)
        source = torch.where(near_inner, outer, inner)
    return target, source, weight


def _vertex_normals(points: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
    """Unit area-weighted vertex normals (3, N) of ``points`` (N, 3); corners: faces.T flattened."""
    a, b, c = points.T.index_select(1, corners).view(3, 3, -1).unbind(dim=1)
    face = torch.linalg.cross(b - a, c - a, dim=0)
    summed = points.new_zeros(3, len(points)).index_add_(1, corners, face.repeat(1, 3))
    return summed * (summed * summed).sum(dim=0).clamp_min(torch.finfo(summed.dtype).tiny).rsqrt()


def _silhouette_flags(corner_j: torch.Tensor, corner_k: torch.Tensor, opposite: torch.Tensor,
                      area2: torch.Tensor) -> torch.Tensor:
    """(2, 3, F) bool, as ``silhouette._silhouette_flags``: edge i is a silhouette and mostly
    vertical ([0]) or horizontal ([1]). corner_j, corner_k: (3 coords, 3, F) rolled corners;
    opposite: (2, 3, F)."""
    rel_j, rel_k = corner_j[:2] - opposite, corner_k[:2] - opposite
    other = rel_j[0] * rel_k[1] - rel_k[0] * rel_j[1]
    silhouette = torch.signbit(other) == torch.signbit(area2)
    extent = (corner_k[:2] - corner_j[:2]).abs_()
    steep = extent[1] >= extent[0]
    return torch.stack([silhouette & steep, silhouette & ~steep])


@dataclass(frozen=True)
class Visibility:
    """What the z-buffer and the silhouette walk decided for one set of vertex positions (no
    gradient): the covered pixels (M,) (``SteadyView.pixel``), their triangles (M,), the covered
    mask (extent,), the triangles' area signs at the pixels (M,), the vertex at each pixel's
    triangle's first corner (M,) (the dump slots' triangle F: vertex 0; its normals are zero
    whatever their offset), the silhouette pairs (the tuple of ``SteadyRenderer._pairs``, K slots),
    each padded pixel's slot in ``pixel`` (extent,) (not covered: past M) and ``face`` with the dump
    slots spread over the real triangles (M,) (``_PixelNormals``' scatter index); and the vertices'
    pixel positions it was found at (V, 2).

    ``slot`` of an uncovered pixel is M + its index modulo ``UNCOVERED_COLUMNS``."""

    pixel: torch.Tensor
    face: torch.Tensor
    covered: torch.Tensor
    sign: torch.Tensor
    first_vertex: torch.Tensor
    pairs: tuple[torch.Tensor, ...]
    slot: torch.Tensor
    spread_face: torch.Tensor
    screen: torch.Tensor


class SteadyView:
    """One call's result: the covered pixels and their normals, and the silhouette blends.

    pixel: (M,) padded flat indices of the covered pixels, ascending (dump slots: the dump pixel);
    face: (M,) their triangles (F: none); covered: (extent,) bool, whether a padded pixel shows a triangle;
    normals: (3, M) unit camera-space normals, not antialiased, differentiable; target, source,
    weight: (K,) blends (no crossing: weight 0); slot: (2, K) the slots in ``pixel`` of target and
    source (M and past: not covered).
    """

    def __init__(self, pixel, face, covered, normals, target, source, weight, slot):
        self.pixel, self.face, self.covered, self.normals = pixel, face, covered, normals
        self.target, self.source, self.weight, self.slot = target, source, weight, slot

    def blended_normals(self) -> torch.Tensor:
        """The normals (3, M) antialiased (the background's normal is 0), as
        ``EdgeCrossings.blend_covered``; differentiable w.r.t. the normals and the weights."""
        padded = torch.nn.functional.pad(self.normals, (0, UNCOVERED_COLUMNS))
        return _BlendColumns.apply(padded, self.slot[0], self.slot[1], self.weight)[:, :-UNCOVERED_COLUMNS]

    def blended_coverage(self, dtype: torch.dtype) -> torch.Tensor:
        """The coverage (extent,) antialiased; differentiable w.r.t. the weights."""
        with torch.no_grad():
            covered = self.covered.to(dtype)
            difference = covered.index_select(0, self.source) - covered.index_select(0, self.target)
        return covered.index_add(0, self.target, self.weight * difference)


class _BlendColumns(torch.autograd.Function):
    """out = values, with out[:, target] += weight · (values[:, source] − values[:, target]) (K
    blends); values (C, M). As ``silhouette._Blend`` along columns."""

    @staticmethod
    def forward(ctx, values, target, source, weight):
        difference = values.index_select(1, source) - values.index_select(1, target)    # (C, K)
        ctx.save_for_backward(target, source, weight, difference)
        return values.index_add(1, target, weight * difference)

    @staticmethod
    def backward(ctx, grad):
        target, source, weight, difference = ctx.saved_tensors
        grad_target = grad.index_select(1, target)                                      # (C, K)
        share = weight * grad_target
        grad_values = grad.index_add(1, torch.cat([source, target]), torch.cat([share, -share], dim=1))
        return grad_values, None, None, (grad_target * difference).sum(dim=0)


def walk_to_silhouette(ring_table: torch.Tensor, count: int, start: torch.Tensor, centre: torch.Tensor,
                       axis: torch.Tensor, direction: torch.Tensor, corner_table: torch.Tensor, fact_table: torch.Tensor
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Follow each pair's segment from its foreground pixel centre through up to 3 triangles to
    the first silhouette edge (as ``silhouette._walk``), evaluating the 13 triangles within two
    edge steps of the start at once. Returns the triangle and edge crossed and whether one of the
    pair's direction class was found (K,). ring_table: (F+1, 13) the triangles within two edge
    steps of each (``SteadyRenderer._ring``); count: F; corner_table: (6, F+1) corner x, y;
    fact_table: (3, F+1) int32 per edge: the neighbour across it × 4 + 2 h + v (the silhouette
    flags). No gradient."""
    ring = ring_table.index_select(0, start)                                        # (K, 13)
    corners = corner_table.index_select(1, ring.view(-1)).view(2, 3, *ring.shape)
    rel = corners - centre[:, None, :, None]                                        # (2, 3, K, 13)
    horizontal = (axis == 0)[:, None]
    frame = torch.where(horizontal, rel, rel.flip(0))                               # along, across
    frame_j, frame_k = frame.roll(-1, 1), frame.roll(-2, 1)
    aj, bj, ak, bk = frame_j[0], frame_j[1], frame_k[0], frame_k[1]
    crosses = torch.signbit(bj) != torch.signbit(bk)
    position = direction[:, None] * (aj * bk - ak * bj) / torch.where(crosses, bk - bj, 1.0)
    position, edge = torch.where(crosses, position, -torch.inf).max(dim=0)          # (K, 13)
    leaves = (position > -_EPS) & (position < 1 + _EPS)
    facts = fact_table.view(-1).index_select(0, (edge * fact_table.shape[1] + ring).view(-1)).view(ring.shape)
    stop = leaves & ((facts & 3) != 0)
    state = torch.stack([stop & ((facts >> torch.where(horizontal, 1, 0)) & 1 != 0),  # found here
                         leaves & ~stop & (facts < 4 * count), edge])               # walk on; edge
    first = state[:, :, 0]                                                          # (3, K)
    node = first[2] + 1
    second = state.gather(2, node[None, :, None].expand(3, -1, 1)).squeeze(2)
    node2 = first[2] * 3 + second[2] + 4
    third = state.gather(2, node2[None, :, None].expand(3, -1, 1)).squeeze(2)
    first, second, third = first != 0, second != 0, third != 0
    at_second = first[1] & second[0]
    at_third = first[1] & second[1] & third[0]
    which = torch.where(first[0], 0, torch.where(at_second, node, node2))
    triangle = ring.gather(1, which[:, None]).squeeze(1)
    edge = edge.gather(1, which[:, None]).squeeze(1)
    return triangle, edge, first[0] | at_second | at_third


def mesh_copies(faces: torch.Tensor, adjacency: MeshAdjacency, copies: int, vertex_count: int
            ) -> tuple[torch.Tensor, MeshAdjacency]:
    """The faces (BF, 3) and adjacency of ``copies`` disjoint copies of a mesh of ``vertex_count``
    vertices, copy b's vertices at b·N (its faces at b·F)."""
    vertex_shift = torch.arange(copies, device=faces.device)[:, None, None] * vertex_count
    face_shift = torch.arange(copies, device=faces.device)[:, None, None] * len(faces)
    neighbor = torch.where(adjacency.neighbor < 0, -1, adjacency.neighbor + face_shift)
    return ((faces + vertex_shift).view(-1, 3),
            MeshAdjacency((adjacency.opposite + vertex_shift).view(-1, 3), neighbor.view(-1, 3)))
