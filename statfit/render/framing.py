"""How a render fit's mesh sits in the map's image: the start checked against the map (units, a
model behind the camera, an initial mesh), and the end refused where the fit ran away."""
from __future__ import annotations

import numpy as np
import torch

from statfit.errors import DivergenceError, StatfitError
from statfit.model.statmodel import StatModel
from statfit.renderer import Camera
from statfit.structures.frame import UNIT_MISMATCH_FACTOR, Frame

MIN_FOREGROUND = 16        # a map's foreground pixels, at least
# A fit whose image ends this many times the map's silhouette across (and twice its start's) ran away:
# a converged fit's image matches the silhouette (a mask model's, within it; a head fitted to a face's
# map, within ~2×); `--lr 10` left a head 6× the silhouette, `--lr 1e6` 1e5× (a finite mesh).
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


def check_framing(template: np.ndarray, camera: Camera, mask: np.ndarray, align: str) -> None:
    """Refuse a mask with too few foreground pixels, a model behind the camera, or one whose image is far
    larger or smaller than the target's silhouette (units?) unless the alignment estimates a scale."""
    if not mask.any():
        raise StatfitError("the normal map's mask has no foreground pixel")
    if (count := int(mask.sum())) < MIN_FOREGROUND:     # no surface, nor its size against the model's (units)
        raise StatfitError(f"the normal map shows {count} foreground pixels: too few (at least {MIN_FOREGROUND})")
    ratio = image_ratio(template, camera, mask)
    if align != "similarity" and not 1 / UNIT_MISMATCH_FACTOR < ratio < UNIT_MISMATCH_FACTOR:
        raise StatfitError(f"the model's image is {ratio:.3g} times the size of the normal map's silhouette: are the "
                           "model and the camera in different units? Rescale one, or use --align similarity")


def check_not_runaway(start: torch.Tensor, end: torch.Tensor, camera: Camera, mask: np.ndarray) -> None:
    """Raise DivergenceError where the fit's image (``end`` (N, 3), in ``camera``'s frame) is more
    than RUNAWAY_IMAGE times the silhouette of ``mask`` across and twice its start's (``start``)."""
    try:
        ratio = image_ratio(end.detach().cpu(), camera, mask)
    except StatfitError:
        raise DivergenceError("the fit diverged: it ended behind the camera (step size too large?)") from None
    if ratio > RUNAWAY_IMAGE and ratio > 2 * image_ratio(start.detach().cpu(), camera, mask):
        raise DivergenceError(f"the fit diverged: its image is {ratio:.3g} times the normal map's silhouette "
                              "across (step size too large?)")


def checked_init(init: np.ndarray, model: StatModel) -> np.ndarray:
    """The initial mesh ``init`` (N, 3) for ``model``, refused in one line unless it is the model's
    topology's, finite and of some extent."""
    init = np.asarray(init, dtype=np.float64)
    if init.shape != model.template.shape:
        raise StatfitError(f"the initial mesh has {init.shape[0]} vertices; the model has {model.num_vertices}")
    if not np.isfinite(init).all():
        raise StatfitError("the initial mesh has NaN or infinite coordinates")
    if not Frame.of(init, model.faces).scale > 1e-9 * model.frame.scale:
        raise StatfitError("the initial mesh's vertices all coincide: a mesh without extent")
    return init
