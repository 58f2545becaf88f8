"""Fits that stay finite but run away (a step size far too large): a mesh fitted to images whose own
image outgrows them. Shared by the image jobs (render, splat); register tests its scan's distance."""
from __future__ import annotations

import numpy as np
import torch

from statfit.errors import DivergenceError, StatfitError
from statfit.renderer import Camera

# A fit whose image ends this many times the map's silhouette across (and twice its start's) ran away:
# a converged fit's image matches the silhouette (a mask model's, within it; a head fitted to a face's
# map, within ~2×); `render --lr 10` left a head several times the silhouette, `--lr 1e6` 1e5×.
RUNAWAY_IMAGE = 3.0


def image_ratio(vertices: np.ndarray | torch.Tensor, camera: Camera, mask: np.ndarray) -> float:
    """The diagonal of the projected bounding box of ``vertices`` (N, 3) in front of ``camera`` over
    that of the foreground of ``mask`` (H, W); raises where most vertices lie behind the camera."""
    pixels, depth = camera.project(torch.as_tensor(vertices, dtype=torch.float64))
    if float(depth.median()) <= 0:
        raise StatfitError("the model lies behind the camera: are the model and the camera in the same frame "
                           "and units?")
    pixels = pixels[depth > 0].numpy()
    rows, cols = np.nonzero(mask)
    return float(np.linalg.norm(np.ptp(pixels, axis=0)) / np.linalg.norm([np.ptp(cols) + 1, np.ptp(rows) + 1]))


def check_not_runaway(start: torch.Tensor, end: torch.Tensor, camera: Camera, mask: np.ndarray) -> None:
    """Raise DivergenceError where the fit's image (``end`` (N, 3), in ``camera``'s frame) is more
    than RUNAWAY_IMAGE times the silhouette of ``mask`` (H, W) across and twice its start's (``start``);
    a mask without foreground tests nothing."""
    if not mask.any():
        return
    try:
        ratio = image_ratio(end.detach().cpu(), camera, mask)
    except StatfitError:
        raise DivergenceError("the fit diverged: it ended behind the camera (step size too large?)") from None
    if ratio > RUNAWAY_IMAGE and ratio > 2 * image_ratio(start.detach().cpu(), camera, mask):
        raise DivergenceError(f"the fit diverged: its image is {ratio:.3g} times the silhouette it was fitted to "
                              "across (step size too large?)")
