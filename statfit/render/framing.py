"""How a render fit's start sits in the map's image: the map's foreground, the model's units and
side of the camera, an initial mesh."""
from __future__ import annotations

import numpy as np

from statfit.core.runaway import image_ratio
from statfit.errors import StatfitError
from statfit.model.statmodel import StatModel
from statfit.renderer import Camera
from statfit.structures.frame import UNIT_MISMATCH_FACTOR, Frame

MIN_FOREGROUND = 16        # a map's foreground pixels, at least


def check_framing(template: np.ndarray, camera: Camera, mask: np.ndarray, align: str) -> None:
    """Refuse a mask with too few foreground pixels, a model behind the camera, or one whose image is
    far larger or smaller than the target's silhouette (units?) unless the alignment estimates a
    scale. ``template``: (M, 3) the start's vertices that triangles use (a vertex no face uses is
    never drawn, wherever it lies)."""
    if not mask.any():
        raise StatfitError("the normal map's mask has no foreground pixel")
    if (count := int(mask.sum())) < MIN_FOREGROUND:     # no surface, nor its size against the model's (units)
        raise StatfitError(f"the normal map shows {count} foreground pixel{'' if count == 1 else 's'}: too few (at least {MIN_FOREGROUND})")
    ratio = image_ratio(template, camera, mask)
    if align != "similarity" and not 1 / UNIT_MISMATCH_FACTOR < ratio < UNIT_MISMATCH_FACTOR:
        raise StatfitError(f"the model's image is {ratio:.3g} times the size of the normal map's silhouette: are the "
                           "model and the camera in different units? Rescale one, or use --align similarity")


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
