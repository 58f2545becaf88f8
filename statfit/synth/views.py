"""Synthetic photographs: a mesh with a generated albedo, lit by a fixed distant light, seen by
cameras spread over the front hemisphere (the test data of ``statfit splat``).

The pictures are :func:`statfit.renderer.images.photograph`'s: the light is fixed in the world, so
the shading is the same from every camera and a splat's single colour can reproduce it (no
view-dependent effects); images are rendered at twice the size and averaged down (antialiased
outlines), the alpha being the covered fraction of each pixel.
"""
from __future__ import annotations

import numpy as np

from statfit.structures.camera import Camera
from statfit.errors import StatfitError
from statfit.structures.frame import Frame
from statfit.synth.sample import camera_for_view

MAX_VIEW_ANGLE = 70.0   # degrees from the front (+z) the cameras reach
GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))
SKIN = np.array([0.78, 0.57, 0.47])


def generated_albedo(vertices: np.ndarray, rng: np.random.Generator, spots: int = 80) -> np.ndarray:
    """Per-vertex colours (N, 3) in [0.02, 0.98]: a skin tone, slow variations, darker spots of
    several sizes (``spots`` of them, at most one a vertex) and fine noise, so that photographs have
    texture to match; made in the shape's unit frame (the same pattern whatever its units)."""
    points = Frame.of(vertices).to_unit(vertices)
    colour = np.tile(SKIN * rng.uniform(0.8, 1.1), (len(points), 1))
    for _ in range(3):
        wave = rng.normal(size=3) * 3.0
        colour *= 1.0 + 0.08 * np.sin(points @ wave + rng.uniform(0, 2 * np.pi))[:, None]
    spots = min(spots, len(points))     # a coarse mesh: a spot on each vertex at most
    centres = points[rng.choice(len(points), spots, replace=False)]
    radii = rng.uniform(0.04, 0.15, spots)
    tints = rng.uniform(0.15, 0.45, (spots, 1)) * np.array([0.6, 1.0, 1.0])
    for centre, radius, tint in zip(centres, radii, tints):   # a few dozen spots, each vectorised over the vertices
        weight = np.exp(-np.square(points - centre).sum(axis=1) / radius**2)[:, None]
        colour *= 1.0 - weight * tint
    colour += rng.uniform(-0.03, 0.03, colour.shape)
    return np.clip(colour, 0.02, 0.98)


def hemisphere_cameras(vertices: np.ndarray, count: int, size: int, fov_deg: float = 30.0) -> list[Camera]:
    """``count`` square cameras looking at the shape's centroid from directions spread evenly (a
    golden-angle spiral) over the cap within :data:`MAX_VIEW_ANGLE` of the front (+z), +y up."""
    if count < 1:
        raise StatfitError(f"the number of views must be at least 1, got {count}")
    heights = 1.0 - (1.0 - np.cos(np.radians(MAX_VIEW_ANGLE))) * (np.arange(count) + 0.5) / count
    turns = GOLDEN_ANGLE * np.arange(count)
    side = np.sqrt(1.0 - heights**2)
    x, y = side * np.cos(turns), side * np.sin(turns)
    yaws, pitches = np.degrees(np.arctan2(x, heights)), np.degrees(np.arcsin(y))
    return [camera_for_view(vertices, yaw, pitch, size, fov_deg) for yaw, pitch in zip(yaws, pitches)]


def held_out_split(count: int, every: int) -> list[str]:
    """'test' for every ``every``-th view (the 3rd, 3 + every, ...; 0: none), 'train' for the rest."""
    return ["test" if every and i % every == min(2, every - 1) else "train" for i in range(count)]
