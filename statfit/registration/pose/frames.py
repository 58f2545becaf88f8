"""The search's poses between unit frames, and a scan's units: the model's unit frame is
u = (x − centre) / scale (:class:`statfit.structures.frame.Frame`), the scan's q = (p − centroid) /
(units · scale), so that no threshold of the search depends on either's units."""
from __future__ import annotations

import numpy as np

from statfit.geometry.align import Similarity
from statfit.structures.frame import Frame

INCH = 2.54                # centimetres: a scan in inches lies this far off a power of ten from a metric model


def landmark_units(scale: float) -> float:
    """The scan's unit relative to the model's, from the ``scale`` of a landmark similarity: the
    power of ten or power of ten over INCH nearest it (landmarks place a person's size within
    ±10%; neighbouring units lie ≥ 2.5 times apart)."""
    power = float(10.0 ** np.round(np.log10(scale)))
    inches = float(10.0 ** np.round(np.log10(scale * INCH))) / INCH
    return power if abs(np.log(scale / power)) <= abs(np.log(scale / inches)) else inches


def to_scan_frame(transform: Similarity, frame: Frame, centroid: np.ndarray, units: float) -> Similarity:
    """A pose between unit frames (model: u = (x − centre)/scale; scan: q = (p − centroid)/(units·scale))
    as the model → scan similarity, written out so that the scale is the unit's exactly (a
    composition would round it)."""
    return Similarity(units * transform.scale, transform.rotation,
                      centroid + units * frame.scale * transform.translation
                      - units * transform.scale * transform.rotation @ frame.center)


def to_unit_frames(transform: Similarity, frame: Frame, centroid: np.ndarray, units: float) -> Similarity:
    """The inverse of :func:`to_scan_frame`: a model → scan similarity as a pose between the unit frames."""
    return Similarity(transform.scale / units, transform.rotation,
                      (transform.scale * transform.rotation @ frame.center + transform.translation - centroid)
                      / (units * frame.scale))
