"""The benchmark cases on the ICT head: an identity sample plus an expression outside the identity
model, seen as a partial scan (4,300 points from one side) or as one normal map. The same seeds and
views as the registration and rendering studies (docs/studies.md)."""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from common import ICT_EXPRESSIONS, ICT_MODEL

# name: (seed, expression, weight, yaw °, pitch °)
SCAN_CASES = {
    "jaw-open": (3, "jawOpen", 1.0, 30.0, 0.0),
    "smile": (11, "mouthSmile_R", 1.0, 0.0, 0.0),
    "brow-up": (23, "browInnerUp_L", 0.9, -40.0, 0.0),
}
# The registration study's other test cases and its three held-out cases (docs/studies.md §1).
STUDY_SCAN_CASES = SCAN_CASES | {
    "cheek-puff": (37, "cheekPuff_L", 1.0, 30.0, 15.0),
    "mouth-left": (41, "mouthLeft", 0.8, 0.0, 15.0),
    "eye-blink": (53, "eyeBlink_L", 1.0, -40.0, 0.0),
    "jaw-forward": (101, "jawForward", 1.0, 20.0, 0.0),
    "frown": (103, "mouthFrown_R", 0.9, -30.0, 10.0),
    "nose-sneer": (107, "noseSneer_R", 1.0, 45.0, 0.0),
}
HELD_OUT_SCAN_CASES = ("jaw-forward", "frown", "nose-sneer")
# The register default until 2026-11-25 (docs/studies.md §9), kept for the studies that compare with it.
FORMER_DEFAULT = "former default (statistical 4,000 + 1,333)"


def former_default_stages() -> tuple:
    from statfit.core.settings import Settings

    return (Settings("statistical", 4000, 0.03, beta=1000.0, mode_gain=1.0),
            Settings("statistical", 1333, 0.01, beta=1000.0, mode_gain=0.5))


def register_named(model, points, name: str, iterations: int | None = None, **options):
    """``statfit.registration.job.register`` with a shipped method or pipeline ``name``, or
    :data:`FORMER_DEFAULT` (its stages as they were; ``iterations`` then replaces each stage's)."""
    from dataclasses import replace

    from statfit.registration.job import register

    if name != FORMER_DEFAULT:
        return register(model, points, name, iterations=iterations, **options)
    stages = former_default_stages()
    if iterations is not None:
        stages = tuple(replace(stage, iterations=iterations) for stage in stages)
    return register(model, points, "default", stages=stages, **options)


NORMAL_CASES = {
    "jaw-open": (3, "jawOpen", 0.8, 20.0, 0.0),
    "smile": (11, "mouthSmile_R", 1.0, 0.0, 0.0),
}


@dataclass(frozen=True)
class ScanCase:
    name: str
    target: np.ndarray  # (N, 3) ground truth
    points: np.ndarray  # (M, 3) partial scan
    observed: np.ndarray  # (N,) bool: vertices the scan sees


@dataclass(frozen=True)
class NormalCase:
    name: str
    target: np.ndarray
    normal_map: object  # statfit.io.normalmap.NormalMap
    camera: object  # statfit.renderer.Camera
    observed: np.ndarray  # (N,) bool: vertices of triangles seen in the map


@lru_cache(maxsize=1)
def ict_model():
    from statfit.model.statmodel import load_model

    return load_model(ICT_MODEL)


def _target(seed: int, expression: str, weight: float) -> tuple[np.ndarray, np.random.Generator]:
    from statfit.synth.sample import load_delta, sample_target

    rng = np.random.default_rng(seed)
    return sample_target(ict_model(), rng, 1.0, load_delta(str(ICT_EXPRESSIONS), expression), weight), rng


def scan_case(name: str) -> ScanCase:
    """The named partial-scan case."""
    from statfit.geometry.metrics import observed_vertices
    from statfit.synth.sample import scan_from_view

    seed, expression, weight, yaw, pitch = STUDY_SCAN_CASES[name]
    target, rng = _target(seed, expression, weight)
    points = scan_from_view(target, ict_model().faces, rng, 4300, yaw, pitch)
    return ScanCase(name, target, points, observed_vertices(target, points))


def normal_case(name: str, size: int) -> NormalCase:
    """The named normal-map case at ``size``² pixels."""
    from statfit.structures.normal_map import NormalMap
    from statfit.geometry.metrics import visible_vertices
    from statfit.synth.sample import camera_for_view
    from statfit.renderer.images import render_target

    seed, expression, weight, yaw, pitch = NORMAL_CASES[name]
    target, _ = _target(seed, expression, weight)
    camera = camera_for_view(target, yaw, pitch, size)
    normal_map = NormalMap(*render_target(target, ict_model().faces, camera))
    return NormalCase(name, target, normal_map, camera, visible_vertices(target, ict_model().faces, camera))


def relative_errors(vertices: np.ndarray, target: np.ndarray, observed: np.ndarray) -> dict[str, float]:
    """Mean vertex error over all / observed / unobserved vertices, divided by the ground truth's
    RMS radius (unit-free; the studies' measure)."""
    scale = float(np.sqrt(((target - target.mean(axis=0)) ** 2).sum(axis=1).mean()))
    err = np.linalg.norm(vertices - target, axis=1) / scale
    return {"all": float(err.mean()), "observed": float(err[observed].mean()),
            "unobserved": float(err[~observed].mean())}
