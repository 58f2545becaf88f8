"""Triangle rasterisation in torch: a vectorised z-buffer, then differentiable interpolation.

Visibility (no gradient): each triangle in front of the near plane is split into the pixel rows
of its screen bounding box; on each row the span of pixel centres inside all three edge functions
is solved for directly, so only covered (triangle, pixel) pairs are enumerated (repeat_interleave,
no Python loops over triangles or pixels). One ``scatter_reduce('amin')`` over a packed
(depth, triangle id) int64 key per pixel then picks the nearest triangle (ties: the lower id).
Rows and pairs are processed in chunks of at most ``max_candidates`` so memory stays bounded
whatever the triangles' sizes.

Differentiable pass: per triangle, the screen-space barycentrics divided by the corner depths
are affine functions of the pixel position, computed from the projected vertices (so gradients
flow through the camera projection to the world-space vertices); a covered pixel evaluates its
triangle's functions at its centre, which gives perspective-correct barycentrics and attributes.

Per-element work is laid out component-major ((3, F), (C, M), ...) so that elementwise ops and
reductions run over long contiguous rows (torch's CPU kernels are slow on tiny trailing dims).
"""
from __future__ import annotations

import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import cached_property

import torch

from statfit.errors import StatfitError
from statfit.structures.camera import Camera

# Z-buffer keys: float32 bits of the (positive) depth in the high word, triangle id in the low word.
# The empty key's words read as depth +inf and triangle -1.
_EMPTY = (0x7F800000 << 32) | 0xFFFFFFFF
_HUGE = 1e30  # bounds beyond any image; stands in for ±inf in span bounds (inf·0 would give nan)


@dataclass(frozen=True, eq=False)
class Fragments:
    """A rasterised view.

    triangle: (H, W) int64 visible triangle per pixel, -1 for background;
    depth: (H, W) camera z of the visible surface at the pixel centre (float32 precision), +inf
    for background;
    pixel: (M,) int64 flat indices (row·W + col) of the covered pixels, ascending;
    face: (M,) int64 their triangles; screen: (N, 2) projected vertices (pixel coordinates),
    differentiable; setup: the triangles' screen-space planes (differentiable), from which
    attributes are interpolated.
    """

    triangle: torch.Tensor
    depth: torch.Tensor
    pixel: torch.Tensor
    face: torch.Tensor
    screen: torch.Tensor
    setup: _TriangleSetup = field(repr=False)

    @property
    def shape(self) -> tuple[int, int]:
        """Image (height, width)."""
        return self.triangle.shape[0], self.triangle.shape[1]

    @cached_property
    def offsets(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Pixel offsets dx, dy (M,) of each covered pixel from its triangle's plane origin."""
        width = self.shape[1]
        row = self.pixel // width
        origin = self.setup.origin.index_select(1, self.face)
        return (self.pixel - row * width).to(origin.dtype) - origin[0], row.to(origin.dtype) - origin[1]

    @cached_property
    def barycentric(self) -> torch.Tensor:
        """Perspective-correct barycentrics (3, M) of the pixel centres w.r.t. the corners of
        their triangles; differentiable."""
        dx, dy = self.offsets
        planes = self.setup.weight.view(9, -1).index_select(1, self.face).view(3, 3, -1)
        value, slope_x, slope_y = planes.unbind(dim=0)                # (3, M) each
        weight = value + dx * slope_x + dy * slope_y
        return weight / weight.sum(dim=0)

    def coverage(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """(H, W, 1) 1 on covered pixels, 0 on the background."""
        return (self.triangle >= 0).to(dtype)[..., None]

    def to_image(self, values: torch.Tensor) -> torch.Tensor:
        """Per-fragment values (C, M) → (H, W, C) image, zero on the background; differentiable."""
        height, width = self.shape
        image = values.new_zeros(height * width, values.shape[0])
        return image.index_copy_(0, self.pixel, values.T).view(height, width, -1)


def rasterize(vertices: torch.Tensor, faces: torch.Tensor, camera: Camera, *, near: float = 1e-3,
              max_candidates: int = 1 << 21) -> Fragments:
    """Rasterise world-space ``vertices`` (N, 3) and ``faces`` (F, 3) long for ``camera``.

    Triangles with a vertex at camera depth ≤ ``near`` (world units) are culled whole (no
    clipping), as are degenerate ones; both windings are drawn. Pixel centres on a triangle's
    edge count as inside. ``max_candidates`` bounds the (triangle, pixel) pairs held at once.
    """
    if vertices.ndim != 2 or vertices.shape[1] != 3 or not vertices.is_floating_point():
        raise StatfitError(f"vertices must be a floating-point (N, 3) tensor, got {vertices.dtype} "
                           f"{tuple(vertices.shape)}")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype != torch.long:
        raise StatfitError(f"faces must be an int64 (F, 3) tensor, got {faces.dtype} {tuple(faces.shape)}")
    height, width = camera.height, camera.width
    points = camera.to_camera(vertices)
    screen = camera.camera_to_pixels(points)
    setup = _TriangleSetup.of(screen, points[:, 2], faces, height, width, near)
    triangle, depth = _zbuffer(setup, height, width, max_candidates)
    pixel = torch.nonzero(triangle.view(-1) >= 0).squeeze(1)
    face = triangle.view(-1).index_select(0, pixel)
    return Fragments(triangle, depth, pixel, face, screen, setup)


@dataclass(frozen=True)
class _TriangleSetup:
    """Per-triangle affine functions of the pixel offset (dx, dy) from the first pixel centre of
    the triangle's screen bounding box.

    barycentric: (3, 3, F) value at that pixel, d/dx, d/dy of the screen-space barycentric of
    each corner (≥ 0 inside, whatever the winding); weight: (3, 3, F) the same for barycentric /
    corner depth, whose sum over the corners is 1/z (affine in screen space) and which normalise
    to the perspective-correct barycentrics. Both differentiable; zero for culled triangles.
    origin: (2, F) first pixel column and row; cols, rows: (F,) int64 bounding box size, zero
    for culled triangles (behind the near plane, degenerate or off screen).
    """

    barycentric: torch.Tensor
    weight: torch.Tensor
    origin: torch.Tensor
    cols: torch.Tensor
    rows: torch.Tensor

    @classmethod
    def of(cls, screen: torch.Tensor, depth: torch.Tensor, faces: torch.Tensor, height: int, width: int,
           near: float) -> _TriangleSetup:
        """screen: (N, 2) pixel coordinates, depth: (N,) camera z of the vertices; faces: (F, 3)."""
        corner_ids = faces.T.reshape(-1)
        x, y = (screen[:, axis].index_select(0, corner_ids).view(3, -1) for axis in (0, 1))
        z = depth.index_select(0, corner_ids).view(3, -1)             # (3, F) each
        with torch.no_grad():
            x_lo, x_hi = _pixel_range(x, width)
            y_lo, y_hi = _pixel_range(y, height)
            cols, rows = (x_hi - x_lo + 1).clamp_min(0), (y_hi - y_lo + 1).clamp_min(0)
            usable = ((z > near).all(dim=0) & (cols > 0) & (rows > 0)
                      & torch.isfinite(x).all(dim=0) & torch.isfinite(y).all(dim=0))
        x = torch.where(usable, x - (x_lo + 0.5), 0.0)                # relative to the first pixel centre
        y = torch.where(usable, y - (y_lo + 0.5), 0.0)
        xj, xk, yj, yk = x.roll(-1, 0), x.roll(-2, 0), y.roll(-1, 0), y.roll(-2, 0)
        value = xj * yk - xk * yj                                     # edge function of the edge j → k
        area2 = value.sum(dim=0)                                      # twice the signed area
        usable = usable & (area2.detach() != 0)
        bary = torch.stack([value, yj - yk, xk - xj]) / torch.where(usable, area2, 1.0)
        weight = bary / torch.where(usable, z, 1.0)
        origin = torch.stack([x_lo, y_lo]).nan_to_num_(0.0, 0.0, 0.0)
        return cls(bary, weight, origin, torch.where(usable, cols, 0).long(), torch.where(usable, rows, 0).long())


def _zbuffer(setup: _TriangleSetup, height: int, width: int, max_candidates: int
             ) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest triangle id (H, W) int64 (-1: none) and its depth (H, W) (+inf: none). No gradient."""
    with torch.no_grad():
        inv_depth = setup.weight.sum(dim=1, keepdim=True)
        planes = torch.cat([setup.barycentric, inv_depth], dim=1).reshape(12, -1)   # [value|d/dx|d/dy] × 4
        table = torch.cat([planes, setup.cols[None].to(planes.dtype)])              # (13, F)
        origin = setup.origin[1].long() * width + setup.origin[0].long()            # flat first pixel
        keys = torch.full((height * width,), _EMPTY, dtype=torch.int64, device=planes.device)
        for tri, dy in _enumerate(setup.rows, max(max_candidates // 4, 1)):
            row = table.index_select(1, tri)                                         # (13, R)
            start = torch.addcmul(row[0:4], dy.to(row.dtype), row[8:12])           # values at the row start
            first, count = _row_span(start[:3], row[4:7], row[12])
            step = row[7]
            pixel_table = torch.stack([origin.index_select(0, tri) + dy * width + first, tri])
            depth_table = torch.stack([start[3] + first * step, step])
            for owner, dx in _enumerate(count, max_candidates):
                base, tri_id = pixel_table.index_select(1, owner)
                inv_start, inv_step = depth_table.index_select(1, owner)
                bits = torch.addcmul(inv_start, dx.to(inv_step.dtype), inv_step).reciprocal_().float()
                key = bits.view(torch.int32).long().bitwise_left_shift_(32).bitwise_or_(tri_id)
                keys.scatter_reduce_(0, base.add_(dx), key, reduce="amin")
        words = keys.view(torch.int32).view(-1, 2)                                  # (low, high) words
        low = 0 if sys.byteorder == "little" else 1
        triangle = words[:, low].long()                                             # empty: -1
        depth = words[:, 1 - low].view(torch.float32).to(planes.dtype)              # empty: +inf
    return triangle.view(height, width), depth.view(height, width)


def _pixel_range(coord: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """First and last pixel index (F,) whose centre lies within the triangles' extent along one
    axis, clipped to [0, size); coord: (3, F). Empty ranges have last < first."""
    low = torch.minimum(torch.minimum(coord[0], coord[1]), coord[2])
    high = torch.maximum(torch.maximum(coord[0], coord[1]), coord[2])
    return (low - 0.5).ceil_().clamp_(min=0), (high - 0.5).floor_().clamp_(max=size - 1)


def _row_span(start: torch.Tensor, step: torch.Tensor, cols: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """First pixel offset and pixel count (R,) int64 where the affine functions ``start + step·x``
    (3, R) are all ≥ 0 for integers x in [0, cols); cols: (R,)."""
    sign = torch.sign(step)
    zero = 1 - sign * sign
    step = step + zero * torch.finfo(step.dtype).tiny                      # zero slope: bound ±huge or 0,
    sign = sign + zero                                                     # and counted as rising
    bound = (-start / step).clamp_(-_HUGE, _HUGE)
    lower = bound.ceil() - (1 - sign) * (2 * _HUGE)                        # x ≥ bound where rising
    upper = bound.floor_() + (1 + sign) * (2 * _HUGE)                      # x ≤ bound where falling
    first = torch.maximum(torch.maximum(lower[0], lower[1]), lower[2]).clamp_(min=0)
    first = torch.minimum(first, cols)
    last = torch.minimum(torch.minimum(upper[0], upper[1]), torch.minimum(upper[2], cols - 1))
    return first.long(), (last - first + 1).clamp_(min=0).long()


def _enumerate(counts: torch.Tensor, budget: int) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
    """All (owner, index) pairs with 0 ≤ index < counts[owner], in chunks of at most ``budget``.

    counts: (K,) int64. Yields owner (P,) and index (P,) int64 tensors.
    """
    ends = torch.cumsum(counts, 0)
    starts = ends - counts
    total = int(ends[-1]) if len(ends) else 0
    for first in range(0, total, budget):
        last = min(first + budget, total)
        in_chunk = (ends.clamp(max=last) - starts.clamp(min=first)).clamp_min(0)
        owner = torch.repeat_interleave(in_chunk, output_size=last - first)
        yield owner, torch.arange(first, last, device=counts.device) - starts.index_select(0, owner)


def interpolate(attributes: torch.Tensor, faces: torch.Tensor, fragments: Fragments) -> torch.Tensor:
    """Vertex attributes (N, C) → (H, W, C) image (perspective-correct), zero on the background."""
    return fragments.to_image(interpolate_fragments(attributes, faces, fragments))


def interpolate_fragments(attributes: torch.Tensor, faces: torch.Tensor, fragments: Fragments, *,
                          normalize: bool = False) -> torch.Tensor:
    """Vertex attributes (N, C) at the covered pixels, (C, M), in ``fragments.pixel`` order;
    with ``normalize``, scaled to unit length per pixel (for directions such as normals).

    Per triangle, Σ_k attribute_k · (barycentric_k / z_k) and Σ_k barycentric_k / z_k = 1/z are
    affine in the pixel offset; each pixel evaluates both and divides (perspective-correct). The
    division by the positive 1/z is skipped when normalising, which cancels it.
    """
    weight = fragments.setup.weight                                   # (3 kinds, 3 corners, F)
    channels, count = attributes.shape[1], weight.shape[2]
    corners = attributes.T.index_select(1, faces.T.reshape(-1)).view(channels, 3, count)
    planes = (weight[:, None] * corners).sum(dim=2)                   # (3 kinds, C, F)
    if not normalize:
        planes = torch.cat([planes, weight.sum(dim=1, keepdim=True)], dim=1)
    rows = planes.shape[1]
    at = planes.view(3 * rows, count).index_select(1, fragments.face).view(3, rows, -1)
    value, slope_x, slope_y = at.unbind(dim=0)                        # (rows, M) each
    dx, dy = fragments.offsets
    scaled = value + dx * slope_x + dy * slope_y                      # (rows, M)
    if normalize:
        return scaled / (scaled * scaled).sum(dim=0).sqrt().clamp_min(torch.finfo(scaled.dtype).tiny)
    numerator, inv_depth = scaled.split([channels, 1])
    return numerator / inv_depth
