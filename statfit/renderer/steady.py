"""The normal-map renderer of a fitting loop: one mesh topology, one camera, many vertex positions.

The same image as ``rasterize`` → ``fragment_normals`` → ``silhouette_crossings(...).blend`` (z-buffer,
perspective-correct normals, analytic antialiasing with the same walk to the silhouette edge), laid
out for a loop that calls it every iteration, on a GPU as on a CPU:

* static shapes: the z-buffer's rows (triangle, bounding-box row) and covered (triangle, pixel)
  pairs, the covered pixels and the pixel pairs examined for silhouette crossings live in buffers
  (:mod:`statfit.renderer.steady_buffers`) sized at the first call (the need measured then ×
  ``MARGIN``, plus ``FLOOR``), enumerated by ``cumsum`` of start marks and addressed with masks
  instead of ``nonzero``, boolean indexing or ``repeat_interleave``. Nothing is read back to the
  host in the steady state except, every ``CHECK_EVERY`` calls, whether the largest need since the
  last check exceeded a buffer (one read); a buffer that did is sized afresh at the next call. The
  calls in between dropped what did not fit: with the margin, that takes a view whose covered area
  grows by a quarter within ``CHECK_EVERY`` steps (a fit moves far less; the alignment's scale step
  of 1% moves ~30%);
* what depends only on the topology or the camera (corner and opposite-vertex indices, the
  triangles within two edge steps of each triangle, pixel centres, the projection) is built once;
* per-pixel and per-pair work is component-major in few, large ops; the walk from a pixel pair to
  its silhouette edge evaluates the whole two-step neighbourhood of the start triangle at once
  (13 triangles) and then follows the path, instead of three dependent rounds; the per-pixel
  normals and the crossing weights have hand-written backward passes.

Images are flat over the pixels of the image padded by one pixel on every side (so neighbours never
need a bounds test), then one dump slot that masked lanes point at (and its neighbours). Masked
lanes that scatter write nothing (a zero, or no key) into distinct real slots instead: CUDA's
deterministic scatters add each slot's writes one after another. On a CPU, where a shared slot
costs nothing, the dump pixels' gradients and the blends into uncovered pixels keep one slot each.

The z-buffer and the pairs are those of the general functions (the same row spans and depth keys:
the same triangle per pixel); the normals are the edge functions' sum, set up per triangle as an
affine function of the pixel centre's offset from the triangle's first corner (not from the
barycentric planes), and the blends are summed in another order, so values differ at float
rounding (float64: within 1e-10, gradients included: tests/test_steady_renderer.py).
"""
from __future__ import annotations

from typing import Sequence

import torch

from statfit.renderer.raster import _EMPTY, _row_span
from statfit.renderer.silhouette import MeshAdjacency
from statfit.renderer.steady_buffers import SteadyBuffers
from statfit.renderer.steady_parts import (UNCOVERED_COLUMNS, SteadyView, Visibility, _columns, _PixelNormals,
                                           _silhouette_flags, _vertex_normals, crossing_blends, mesh_copies,
                                           walk_to_silhouette)
from statfit.structures.camera import Camera

_LOW32 = 0xFFFFFFFF


class SteadyRenderer(SteadyBuffers):
    """Antialiased camera-space normals and coverage of a fixed mesh topology in a fixed camera.

    faces: (F, 3) long; adjacency: ``MeshAdjacency.from_faces(faces)``; dtype: the vertices'. Call
    with vertices (N, 3) → :class:`SteadyView`.

    With B cameras of one image size (and ``vertex_count`` N), B meshes of one topology in one call:
    vertices (B, N, 3), each drawn in its own camera into its own image, the B padded images stacked
    (mesh b's triangles are b·F + its own, its image's padded pixels b·``view_pixels`` + its own),
    so every buffer, op and launch serves all B views.
    """

    def __init__(self, faces: torch.Tensor, camera: Camera | Sequence[Camera], adjacency: MeshAdjacency,
                 dtype: torch.dtype, near: float = 1e-3, vertex_count: int | None = None):
        cameras = [camera] if isinstance(camera, Camera) else list(camera)
        height, width = cameras[0].height, cameras[0].width
        if any((each.height, each.width) != (height, width) for each in cameras):
            raise ValueError("the views rendered together must have one image size")
        views = len(cameras)
        if views > 1:
            if vertex_count is None:
                raise ValueError("several views need the vertex count of one mesh")
            faces, adjacency = mesh_copies(faces, adjacency, views, vertex_count)
        device = faces.device
        super().__init__(device)
        self.dtype, self.near, self.views = dtype, near, views
        self.height, self.width = height, width
        self.stride = stride = width + 2
        self.view_pixels = view_pixels = (height + 2) * stride          # one padded image
        self.pixels = pixels = views * view_pixels                      # the images stacked; slot ``pixels``: dump
        count = len(faces)
        self.count = count
        long = dict(dtype=torch.long, device=device)
        pose = torch.stack([each.world_to_camera for each in cameras]).to(device=device, dtype=dtype)
        K = torch.stack([each.K for each in cameras]).to(device=device, dtype=dtype)
        self._rotation_t = pose[:, :3, :3].transpose(1, 2).contiguous()                  # (B, 3, 3)
        self._translation = pose[:, None, :3, 3].contiguous()                            # (B, 1, 3)
        self._focal_t = K[:, :2, :2].transpose(1, 2).contiguous()                        # (B, 2, 2)
        self._principal = K[:, None, :2, 2].contiguous()                                 # (B, 1, 2)
        if views == 1:
            self._rotation_t, self._translation = self._rotation_t[0], self._translation[0, 0]
            self._focal_t, self._principal = self._focal_t[0], self._principal[0, 0]
        # The padded first pixel of each triangle's view (B > 1): its image's offset in the stack.
        self._view_origin = (torch.arange(views, **long) * view_pixels).repeat_interleave(count // views) \
            if views > 1 else None
        self._last_pixel = torch.tensor([[width - 1], [height - 1]], dtype=dtype, device=device)
        corners = faces.T.reshape(-1)
        self._corners = corners                                        # (3F,) corner-major
        self._gather = torch.cat([corners, adjacency.opposite.T.reshape(-1)])     # corners, then opposites
        padded = torch.cat([faces, faces.new_zeros(1, 3)])             # triangle F: none (vertex 0 thrice)
        self._padded_corners = padded.T.reshape(-1)                    # (3(F+1),) corner-major
        # Endpoints of edge e (corner e+1 → e+2) of triangle t at row 3t + e.
        self._edge_ends = torch.stack([padded.roll(-1, 1), padded.roll(-2, 1)], dim=2).reshape(-1, 2)
        neighbor = torch.cat([torch.where(adjacency.neighbor < 0, count, adjacency.neighbor),
                              torch.full((1, 3), count, **long)])          # (F+1, 3), none → F
        self._neighbor_t = neighbor.T.int().contiguous()                    # (3, F+1) int32
        self._neighbor_flat = neighbor.T.reshape(-1).contiguous()             # (3(F+1),) edge-major
        second = neighbor.index_select(0, neighbor.reshape(-1)).view(-1, 9)
        # The triangles within two edge steps: self, across edge e (1 + e), then across its edge f (4 + 3e + f).
        self._ring = torch.cat([torch.arange(count + 1, **long)[:, None], neighbor, second], dim=1).contiguous()
        self.extent = extent = pixels + stride + 1                      # the dump slot's neighbours too
        index = torch.arange(extent, **long)
        local = index - (index // view_pixels).clamp_max_(views - 1) * view_pixels     # within its view's image
        col, row = local % stride - 1, local // stride - 1
        self._centre = torch.stack([col, row]).to(dtype) + 0.5         # (2, extent)
        self._in_image = (col >= 0) & (col < width) & (row >= 0) & (row < height)
        self._pixel_index = index
        # The four neighbours of a pixel: +x, -x, +y, -y; row 4: a masked lane.
        self._offset = torch.tensor([1, -1, stride, -stride, 0], **long)
        self._before = torch.tensor([[0], [1], [0], [1]], **long)     # the neighbour comes first in the pair
        self._axis = torch.tensor([0, 0, 1, 1, 0], **long)
        self._direction = torch.tensor([1.0, -1.0, 1.0, -1.0, 1.0], dtype=dtype, device=device)
        self._axis_bits = torch.tensor([[0], [0], [1], [1]], dtype=torch.uint8, device=device)  # code bit
        self._visible: Visibility | None = None

    # --- the view -----------------------------------------------------------------------------------------

    def __call__(self, vertices: torch.Tensor, refresh: bool = True, moved: float | None = None) -> SteadyView:
        """The view of ``vertices`` (N, 3), or (B, N, 3). ``refresh`` False: with the visibility of
        the last refreshed call (which pixel shows which triangle, the silhouette pairs and the
        edges they cross, :class:`Visibility`): the normals and the crossings move with the
        vertices, the pixels they are drawn at do not (the fitting loop's reuse, docs/method.md);
        unless a vertex has moved more than ``moved`` pixels since that refresh (one host read)."""
        camera_points, depth, screen = self._project(vertices)
        normals = _vertex_normals(camera_points, self._corners)                          # (3, N)
        if not refresh and moved is not None and self._visible is not None:
            with torch.no_grad():
                refresh = bool((screen - self._visible.screen).abs().amax() > moved)
        if refresh or self._visible is None:
            with torch.no_grad():
                # The kept positions detached: a Visibility kept past this iteration must not hold its
                # autograd graph (a graph alive across a CUDA graph's capture ties the parameters'
                # gradient to the warm-up's stream: torch warns, and may wait for that stream).
                self._visible = self._visibility(screen.detach(), depth)
        seen = self._visible
        data = torch.cat([screen.T, depth.T, normals])                                  # (6, N)
        with torch.no_grad():
            offset = self._centre.index_select(1, seen.pixel) - screen.T.index_select(1, seen.first_vertex)
        pixel_normals = _PixelNormals.apply(data, seen.face, self._padded_corners, offset, seen.sign, seen.spread_face)
        target, source, weight = crossing_blends(screen, seen.pairs, self._edge_ends)
        with torch.no_grad():
            slot = seen.slot.index_select(0, torch.cat([target, source])).view(2, -1)    # not covered: ≥ M
        return SteadyView(seen.pixel, seen.face, seen.covered, pixel_normals, target, source, weight, slot)

    def _visibility(self, screen: torch.Tensor, depth: torch.Tensor) -> Visibility:
        """The z-buffer's covered pixels and the silhouette pairs at ``screen`` (V, 2), ``depth`` (V, 1)."""
        count = self.count
        table = torch.cat([screen, depth], dim=1).T                                      # (3, N)
        gathered = table.index_select(1, self._gather).view(3, 2, 3, count)
        corner, opposite = gathered[:, 0], gathered[:2, 1]                              # (3, 3, F), (2, 3, F)
        corner_j, corner_k = corner.roll(-1, 1), corner.roll(-2, 1)
        keys, area2, raster_need = self._zbuffer(corner)
        flags = _silhouette_flags(corner_j, corner_k, opposite, area2)                   # (2, 3, F)
        # Per triangle edge: the neighbour across it × 4 + 2 · (silhouette, steep) + (silhouette, flat).
        facts = torch.nn.functional.pad(flags[0].int().mul_(2).add_(flags[1].int()), (0, 1))
        walk = (torch.nn.functional.pad(corner[:2].reshape(6, count), (0, 1)),          # corner x, y rows
                facts.add_(self._neighbor_t, alpha=4))                                   # (3, F+1) int32
        # The key's low word: the triangle, or all ones (the background) → F.
        triangle = keys.bitwise_and(_LOW32).clamp_max_(count)
        covered = triangle < count
        # Covered pixels, ascending, into a buffer of M slots (dump slots: the dump pixel).
        pixel, running, slot = self._select(covered, "pixels", slot_map=True)          # lanes: pixels; pixel → slot
        if self.lookups:    # a blend into an uncovered pixel writes a column past the covered slots, one of a few
            slot = torch.where(covered, slot, slot + self._spread(len(slot), UNCOVERED_COLUMNS))
        pixel.clamp_max_(self.pixels)
        face = triangle.index_select(0, pixel)
        sign = torch.cat([area2.sign(), area2.new_ones(1)]).index_select(0, face)
        first_vertex = self._padded_corners.index_select(0, face)      # corner 0 of each (F: vertex 0)
        spread_face = torch.where(face < count, face, self._spread(len(face), count)) if self.lookups else face
        pairs, pair_need = self._pairs(keys, pixel, face, flags, walk)
        self._check(torch.cat([raster_need, running[-1:], pair_need]))
        return Visibility(pixel, face, covered, sign, first_vertex, pairs, slot, spread_face, screen)

    def _project(self, vertices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Camera-space points (V, 3), their depths (V, 1) and pixel positions (V, 2) of ``vertices``
        (N, 3), or (B, N, 3) for B views (then V = BN, view-major)."""
        if self.views == 1:
            camera_points = torch.addmm(self._translation, vertices, self._rotation_t)
            depth = camera_points[:, 2:]
            return camera_points, depth, camera_points[:, :2].mm(self._focal_t) / depth + self._principal
        camera_points = torch.baddbmm(self._translation, vertices, self._rotation_t)    # (B, N, 3)
        depth = camera_points[..., 2:]
        screen = camera_points[..., :2].bmm(self._focal_t) / depth + self._principal
        return camera_points.view(-1, 3), depth.reshape(-1, 1), screen.view(-1, 2)

    def _zbuffer(self, corner: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Packed (depth bits, triangle) keys (extent,) of the nearest triangle per pixel
        (``_EMPTY``: none), twice the triangles' signed screen areas (F,) and the buffers' needs
        (2,). As ``raster._zbuffer``: per triangle, the screen-space barycentrics / corner depth
        are planes in the offset from the first pixel centre of its bounding box; each row of the
        box solves for its span of covered pixel centres; the covered pixels are enumerated. No
        gradient."""
        count = self.count
        low, high = corner[:2].amin(dim=1), corner[:2].amax(dim=1)       # (2, F) each; aminmax: ~20× slower on a CPU
        first = (low - 0.5).ceil_().clamp_min_(0)
        size = ((high - 0.5).floor_().minimum(self._last_pixel) - first + 1).clamp_min_(0)   # cols, rows
        rel = corner[:2] - (first + 0.5)[:, None]                                       # (2, 3, F)
        (xj, yj), (xk, yk) = rel.roll(-1, 1), rel.roll(-2, 1)
        value = xj * yk - xk * yj                                                       # edge functions
        area2 = value.sum(dim=0)                                                        # twice the signed area
        usable = torch.cat([(high - low) < torch.inf, corner[2] > self.near]).all(dim=0) & (area2 != 0)
        planes = torch.stack([value, yj - yk, xk - xj]) / (torch.where(usable, area2, 1.0) * corner[2])
        cols, rows = torch.where(usable, size, 0).long()
        # Rows: the planes' values at the row's first pixel and their x slopes, 1/z's too.
        owner, dy, rows_need = self._owners(rows, "rows")
        origin = first[1].long() * self.stride + first[0].long() + (self.stride + 1)   # padded first pixel
        if self.views > 1:
            origin += self._view_origin
        integers = torch.nn.functional.pad(torch.stack([cols, origin]), (0, 1))
        floats = torch.nn.functional.pad(planes.view(9, count), (0, 1))
        width, origin = _columns(integers, owner)
        value, slope_x, slope_y = floats.index_select(1, owner).view(3, 3, -1)          # (3, R) each
        start = torch.addcmul(value, slope_y, dy.to(value.dtype))
        span_first, span_count = _row_span(start, slope_x, width.to(value.dtype))
        inverse = torch.cat([start, slope_x]).view(2, 3, -1).sum(dim=1)                # 1/z at x = 0, its slope
        rows_table = torch.stack([origin + dy * self.stride + span_first, owner])
        depth_table = torch.stack([torch.addcmul(inverse[0], span_first.to(value.dtype), inverse[1]), inverse[1]])
        # Covered pixels of the rows.
        row, dx, pixels_need = self._owners(torch.where(owner < count, span_count, 0), "candidates")
        base, triangle = _columns(torch.nn.functional.pad(rows_table, (0, 1), value=self.pixels), row)
        inverse_start, inverse_step = torch.nn.functional.pad(depth_table, (0, 1), value=1.0).index_select(1, row)
        depth_bits = torch.addcmul(inverse_start, dx.to(inverse_step.dtype), inverse_step).reciprocal_().float()
        key = depth_bits.view(torch.int32).long().bitwise_left_shift_(32).bitwise_or_(triangle)
        inside = row < len(owner)
        keys = torch.full((self.extent,), _EMPTY, dtype=torch.int64, device=self.device)
        # Lanes past the need offer no key (_EMPTY), each to its own pixel.
        keys.scatter_reduce_(0, torch.where(inside, base + dx, self._spread(len(row), self.extent)),
                             torch.where(inside, key, _EMPTY), reduce="amin")
        return keys, area2, torch.stack([rows_need, pixels_need])

    def _pairs(self, keys: torch.Tensor, pixel: torch.Tensor, face: torch.Tensor, flags: torch.Tensor,
               walk: tuple[torch.Tensor, torch.Tensor]) -> tuple[tuple[torch.Tensor, ...], torch.Tensor]:
        """The adjacent pixel pairs whose segment meets a silhouette edge of their direction class,
        in a buffer of K slots: inner (the foreground pixel), outer, axis, direction (±1), the inner
        pixel centre (2, K), the triangle and edge crossed, and whether the slot holds such a pair
        (K,); and the buffers' needs (2,). No gradient."""
        count = self.count
        # Bit c of a triangle's code: a silhouette edge of class c (0 steep, 1 flat) lies within two
        # edge steps of it (two rounds of or-ing the neighbours' codes).
        flags = flags.any(dim=1).to(torch.uint8)                                        # (2, F)
        code = torch.nn.functional.pad(flags[0].bitwise_or_(flags[1] << 1), (0, 1))    # (F+1,)
        for _ in range(2):
            around = code.index_select(0, self._neighbor_flat).view(3, -1)
            code = around[0] | around[1] | around[2] | code
        # Only the covered pixels whose triangle lies within two edge steps of a silhouette edge
        # start a pair: those, into a buffer of their own (dump: the dump pixel, triangle F).
        near = code.index_select(0, face) != 0
        lane, running, _ = self._select(near, "edges")
        pixel = torch.nn.functional.pad(pixel, (0, 1), value=self.pixels).index_select(0, lane)
        face = torch.nn.functional.pad(face, (0, 1), value=count).index_select(0, lane)
        edges_need, slots_m = running[-1], len(lane)
        key_p = keys.index_select(0, pixel)                                             # (M,)
        neighbour = pixel + self._offset[:4, None]                                      # (4, M)
        key_q = keys.index_select(0, neighbour.view(-1)).view(4, -1)
        # The pixel is the foreground one: nearer (ties: the later of the two in the pair), or alone.
        front = (key_q >> 32) > ((key_p >> 32) - self._before)
        differ = (key_q & _LOW32) != (key_p & _LOW32)
        found = front & differ & self._in_image.index_select(0, neighbour.view(-1)).view(4, -1)
        found &= (code.index_select(0, face) >> self._axis_bits).bitwise_and_(1) != 0
        chosen, running, _ = self._select(found.view(-1), "pairs")                     # 4M: masked
        lanes = 4 * slots_m
        direction_id = chosen.div(slots_m, rounding_mode="floor")                      # 4: masked
        used = chosen < lanes
        # A masked slot pairs a pixel with itself (direction 4: no offset), each its own pixel (of
        # those in the buffer: the need may exceed it until the next check).
        spare = self._arange(len(chosen)) % edges_need.clamp(1, slots_m)
        m = torch.where(used, chosen - direction_id * slots_m, spare)
        inner = pixel.index_select(0, m)
        outer = inner + self._offset.index_select(0, direction_id)
        axis = self._axis.index_select(0, direction_id)
        direction = self._direction.index_select(0, direction_id)
        start = face.index_select(0, m)
        centre = self._centre.index_select(1, inner)                                    # (2, K)
        triangle, edge, hit = walk_to_silhouette(self._ring, count, start, centre, axis, direction, *walk)
        hit &= used
        triangle = torch.where(hit, triangle, self._spread(len(hit), count))     # no crossing: any, each its own
        return (inner, outer, axis, direction, centre, triangle, edge, hit), torch.stack([edges_need, running[-1]])
