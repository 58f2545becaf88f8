"""Differentiable rendering of 2D Gaussian surfels (2DGS, Huang et al. 2024) in pure torch, CPU
and CUDA from one code path.

A surfel is a flat Gaussian disc: centre c, orthonormal tangents t_u, t_v, scales s_u, s_v. Its
local coordinates at a pixel come from the exact intersection of the pixel's ray with the disc's
plane, so a surfel seen at a grazing angle is a thin ellipse, not a blob (the reason to prefer
surfels over 3D Gaussians for splats that live on a mesh's triangles: their normal *is* the
surface's). The 2DGS object-space low-pass filter, ``max(G(u, v), exp(−‖x − π(c)‖²))``, keeps a
surfel seen edge-on, or smaller than a pixel, at least one pixel wide.

Binning (no gradient): every surfel's screen bounding box holds the projection of its 3.33σ
parallelogram (conservative for a convex set in front of the camera) and the low-pass footprint,
the extents beyond which α < 1/255 (so binning changes nothing); the (surfel, pixel) pairs inside
are enumerated with ``repeat_interleave`` and kept where α ≥ 1/255. Compositing: the pairs are sorted by (pixel, surfel depth); the transmittance is a
segmented exclusive cumulative product (a cumulative sum of log(1 − α) in float64, per pixel),
contributions stop once the transmittance falls below 1e-4, and colours are summed per pixel with
``index_add``. Everything after binning is ordinary autograd, so gradients reach the surfels'
centres, tangents, scales, colours and opacities (and through them a mesh's vertices).
Per-element work is component-major ((3, M)), as in :mod:`statfit.renderer.raster`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from statfit.structures.camera import Camera
from statfit.errors import StatfitError

MIN_ALPHA = 1.0 / 255.0  # pairs below this opacity are dropped (as in 3DGS and 2DGS)
# Beyond these, even an opaque surfel's α is below MIN_ALPHA, so binning drops no pair that counts:
EXTENT = math.sqrt(2 * math.log(1 / MIN_ALPHA))       # σ: exp(−r²/2) < 1/255 (3.33σ)
LOWPASS_RADIUS = math.sqrt(math.log(1 / MIN_ALPHA))   # pixels: exp(−r²) < 1/255 (2.35 px)
MAX_ALPHA = 0.99
MIN_TRANSMITTANCE = 1e-4  # compositing stops where less light than this is left
MAX_PAIRS = 1 << 24


@dataclass(frozen=True)
class Surfels:
    """P surfels in world space: centres (P, 3), orthonormal tangents tangent_u, tangent_v (P, 3),
    scales (P, 2) (σ along each tangent), colours (P, C), opacity (P,) in [0, 1]."""

    centres: torch.Tensor
    tangent_u: torch.Tensor
    tangent_v: torch.Tensor
    scales: torch.Tensor
    colours: torch.Tensor
    opacity: torch.Tensor

    def __len__(self) -> int:
        return self.centres.shape[0]


@dataclass(frozen=True)
class SplatImage:
    """colour (H, W, C) composited over the background, alpha (H, W) the accumulated opacity,
    pairs the number of (surfel, pixel) contributions composited."""

    colour: torch.Tensor
    alpha: torch.Tensor
    pairs: int


def render_surfels(surfels: Surfels, camera: Camera, background: torch.Tensor | None = None, *,
                   cull_backfaces: bool = True, near: float = 1e-3, max_pairs: int = MAX_PAIRS) -> SplatImage:
    """Render ``surfels`` seen by ``camera``; differentiable w.r.t. every surfel tensor.

    ``background`` (C,) defaults to black. ``cull_backfaces`` drops surfels whose normal
    t_u × t_v faces away from the camera (bound to a consistently wound mesh, those are the back
    of the surface). Surfels with their centre at camera depth ≤ ``near`` are dropped. Raises
    StatfitError when more than ``max_pairs`` (surfel, pixel) pairs would be needed.
    """
    height, width = camera.height, camera.width
    dtype, device = surfels.centres.dtype, surfels.centres.device
    channels = surfels.colours.shape[1]
    pose = camera.world_to_camera.to(dtype=dtype, device=device)
    K = camera.K.to(dtype=dtype, device=device)
    rotation = pose[:3, :3]
    # Per surfel, component-major (3, P): centre, scaled axes a = s_u R t_u, b = s_v R t_v, normal a × b.
    centre = (surfels.centres @ rotation.T + pose[:3, 3]).T
    axis_a = (surfels.tangent_u @ rotation.T).T * surfels.scales[:, 0]
    axis_b = (surfels.tangent_v @ rotation.T).T * surfels.scales[:, 1]
    normal = torch.linalg.cross(axis_a, axis_b, dim=0)
    keep, low, high = _screen_boxes(centre.detach(), axis_a.detach(), axis_b.detach(), normal.detach(), K,
                                    height, width, cull_backfaces, near)
    index = torch.nonzero(keep).squeeze(1)
    splat, pixel, rays = _pairs(low.index_select(1, index), high.index_select(1, index), K, width, max_pairs)
    splat = index.index_select(0, splat)
    alpha = _pair_alpha(splat, pixel, rays, centre, axis_a, axis_b, normal, surfels.opacity, K, width)
    kept = torch.nonzero(alpha.detach() >= MIN_ALPHA).squeeze(1)
    splat, pixel, alpha = splat.index_select(0, kept), pixel.index_select(0, kept), alpha.index_select(0, kept)
    weight, pixel, splat = _composite(splat, pixel, alpha, centre[2].detach(), len(surfels))
    colour = surfels.colours.new_zeros(channels, height * width)
    colour = colour.index_add(1, pixel, surfels.colours.T.index_select(1, splat) * weight)
    coverage = weight.new_zeros(height * width).index_add(0, pixel, weight)
    if background is not None:
        colour = colour + background.to(colour)[:, None] * (1.0 - coverage)
    return SplatImage(colour.T.reshape(height, width, channels), coverage.view(height, width), int(weight.numel()))


def _screen_boxes(centre: torch.Tensor, axis_a: torch.Tensor, axis_b: torch.Tensor, normal: torch.Tensor,
                  K: torch.Tensor, height: int, width: int, cull_backfaces: bool, near: float
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Which surfels to draw (P,) and their pixel-index boxes low, high (2, P) (inclusive, in the
    image): the projected ±EXTENT·σ parallelogram and the low-pass footprint around the projected centre."""
    signs = torch.tensor([[1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0]], dtype=centre.dtype,
                         device=centre.device)
    corners = centre[:, None] + EXTENT * (axis_a[:, None] * signs[:, 0, None] + axis_b[:, None] * signs[:, 1, None])
    points = torch.cat([centre[:, None], corners], dim=1)                       # (3, 5, P)
    keep = (points[2] > near).all(dim=0)
    if cull_backfaces:
        keep &= (normal * centre).sum(dim=0) < 0
    depth = points[2].clamp_min(near)
    pixels = torch.einsum("ij,jkp->ikp", K[:2, :2], points[:2] / depth) + K[:2, 2, None, None]   # (2, 5, P)
    low = torch.minimum(pixels.amin(dim=1), pixels[:, 0] - LOWPASS_RADIUS)
    high = torch.maximum(pixels.amax(dim=1), pixels[:, 0] + LOWPASS_RADIUS)
    # Pixel i has its centre at i + 0.5: the box holds the indices whose centres lie in [low, high].
    size = torch.tensor([width, height], dtype=centre.dtype, device=centre.device)[:, None]
    low = torch.ceil(low - 0.5).clamp(min=0).minimum(size)
    high = torch.floor(high - 0.5).clamp(max=size - 1)
    keep &= (high >= low).all(dim=0)
    return keep, low.long(), high.long()


def _pairs(low: torch.Tensor, high: torch.Tensor, K: torch.Tensor, width: int, max_pairs: int
           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every (surfel, pixel) pair of the boxes (2, S): surfel positions in the box list (M,), flat
    pixel indices (M,) and the pixels' camera-space ray directions (3, M) with z = 1."""
    extent = (high - low + 1).clamp_min(0)
    counts = extent[0] * extent[1]
    total = int(counts.sum())
    if total > max_pairs:
        raise StatfitError(f"rendering needs {total:,} (splat, pixel) pairs, more than {max_pairs:,}: lower the "
                           "image size or use fewer or smaller splats")
    splat = torch.repeat_interleave(torch.arange(len(counts), device=low.device), counts, output_size=total)
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(total, device=low.device) - first.index_select(0, splat)
    box_width = extent[0].index_select(0, splat)
    col = low[0].index_select(0, splat) + local % box_width
    row = low[1].index_select(0, splat) + torch.div(local, box_width, rounding_mode="floor")
    K_inv = torch.linalg.inv(K)
    centres = torch.stack([col, row]).to(K.dtype) + 0.5
    rays = K_inv[:, :2] @ centres + K_inv[:, 2, None]
    return splat, row * width + col, rays / rays[2]


def _pair_alpha(splat: torch.Tensor, pixel: torch.Tensor, rays: torch.Tensor, centre: torch.Tensor,
                axis_a: torch.Tensor, axis_b: torch.Tensor, normal: torch.Tensor, opacity: torch.Tensor,
                K: torch.Tensor, width: int) -> torch.Tensor:
    """α (M,) of every pair: opacity × max(surfel Gaussian at the ray–plane hit, low-pass filter)."""
    # With r = t·d − c on the plane n·x = n·c (t = n·c / n·d): u = r·a/‖a‖², v = r·b/‖b‖². A splat of
    # a zero-area triangle has no axes (a = b = 0): 0, not 0/0, whose NaN its gradient would spread.
    tiny = torch.finfo(axis_a.dtype).tiny
    dir_a = axis_a / axis_a.square().sum(dim=0).clamp_min(tiny)
    dir_b = axis_b / axis_b.square().sum(dim=0).clamp_min(tiny)
    per_splat = torch.cat([normal, dir_a, dir_b, torch.stack([(normal * centre).sum(dim=0),
                                                              (dir_a * centre).sum(dim=0),
                                                              (dir_b * centre).sum(dim=0)])])   # (12, P)
    values = per_splat.index_select(1, splat)
    n, a, b, offsets = values[0:3], values[3:6], values[6:9], values[9:12]
    facing = (n * rays).sum(dim=0)
    grazing = facing.detach().abs() < 1e-8
    depth = offsets[0] / torch.where(grazing, torch.ones_like(facing), facing)
    u = depth * (a * rays).sum(dim=0) - offsets[1]
    v = depth * (b * rays).sum(dim=0) - offsets[2]
    on_plane = torch.where(grazing | (depth.detach() <= 0), torch.zeros_like(u), torch.exp(-0.5 * (u * u + v * v)))
    projected = (K[:2, :2] @ (centre[:2] / centre[2]) + K[:2, 2, None]).index_select(1, splat)   # (2, M)
    row = torch.div(pixel, width, rounding_mode="floor")
    delta_x = (pixel - row * width).to(rays.dtype) + 0.5 - projected[0]
    delta_y = row.to(rays.dtype) + 0.5 - projected[1]
    lowpass = torch.exp(-(delta_x * delta_x + delta_y * delta_y))
    return (opacity.index_select(0, splat) * torch.maximum(on_plane, lowpass)).clamp(max=MAX_ALPHA)


def _composite(splat: torch.Tensor, pixel: torch.Tensor, alpha: torch.Tensor, depth: torch.Tensor, count: int
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Front-to-back compositing weights T·α (M,) of the pairs, and the pairs' pixels and surfels,
    in (pixel, depth) order; T is the light left in front of each pair (exclusive product of 1 − α)."""
    rank = splat.new_empty(count)
    rank[torch.argsort(depth, stable=True)] = torch.arange(count, device=splat.device)
    order = torch.argsort(pixel * count + rank.index_select(0, splat))
    splat, pixel, alpha = splat.index_select(0, order), pixel.index_select(0, order), alpha.index_select(0, order)
    log_left = torch.log1p(-alpha.double())
    before = torch.cumsum(log_left, 0) - log_left                      # Σ over all earlier pairs
    starts = torch.ones_like(pixel, dtype=torch.bool)
    starts[1:] = pixel[1:] != pixel[:-1]
    first = torch.nonzero(starts).squeeze(1)
    segment = torch.cumsum(starts.long(), 0) - 1
    transmittance = torch.exp(before - before.index_select(0, first.index_select(0, segment))).to(alpha.dtype)
    weight = torch.where(transmittance.detach() >= MIN_TRANSMITTANCE, transmittance * alpha,
                         torch.zeros_like(alpha))
    return weight, pixel, splat
