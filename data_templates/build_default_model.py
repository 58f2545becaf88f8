"""Build ``default_head.npz``, the synthetic statistical head model embedded in statfit.

The model is entirely synthetic: no scan, photograph or published model went into it.
It is generated in four steps, all deterministic:

1. **Topology.** A geodesic sphere (icosahedron, every face split at ``FREQUENCY``) is
   remapped by a conformal (Möbius) map that moves vertices towards ``+z``: the face gets
   about 2.8 times the vertex density of a uniform sphere, the back of the head less.
2. **Parametric head.** Each vertex keeps its unit direction ``u``; a head is the radial
   surface ``x = (r0(u) + h(u)) u`` where ``r0`` is a super-ellipsoid skull and ``h`` a sum of
   smooth Gaussian bumps (brow, eye sockets, nose, cheeks, lips, chin, ears, neck), followed by
   smooth orientation-preserving warps (jaw taper, anisotropic scaling).  A radial surface over
   a valid spherical triangulation cannot fold, so every head is a valid mesh; the script also
   checks that no triangle of any head faces the opposite way to the mean's.
3. **Population.** ``NUM_SHAPES`` heads are drawn from a seeded generator.  Every feature
   parameter mixes a few shared latent factors (size, robustness, face length, adiposity,
   nasal prominence, orbital depth) with its own noise, so features are correlated (a robust
   head has a wider jaw, a heavier brow and a larger nose).  A low-frequency random field (fixed
   smooth kernels with random weights) adds individual variation that no feature describes.
4. **PCA.** The population is centred on its mean and decomposed with an SVD; the first
   ``NUM_MODES`` directions, scaled by their standard deviations, become ``shapedirs``.

Units are metres, ``+y`` is up and ``+z`` points out of the face.
Run ``python data_templates/build_default_model.py [--out PATH]`` to regenerate.
"""
from __future__ import annotations

import argparse
import itertools
import os
import time
from pathlib import Path

# The matrices are small: one BLAS thread is fastest (multi-threaded OpenBLAS stalls on a busy
# machine), and the numbers then do not depend on the machine's core count.
for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import numpy as np  # noqa: E402  (after the thread settings, which numpy reads on import)

from statfit.io.files import write_atomic  # noqa: E402
from statfit.io.npz import npz_bytes  # noqa: E402
from statfit.model.pca import principal_components  # noqa: E402

SEED = 5023
NUM_SHAPES = 300
NUM_MODES = 50
FREQUENCY = 22  # 10 * 22**2 + 2 = 4842 vertices
FRONT_FOCUS = 0.6  # Möbius contraction; vertex density at +z grows by 1 / FRONT_FOCUS**2
FIELD_KERNELS = 32  # smooth kernels of the individual random field
FIELD_CONCENTRATION = 6.0  # von Mises-Fisher concentration of those kernels
FIELD_STD = 0.0012  # metres, per kernel weight

LATENTS = ("size", "robustness", "face_length", "adiposity", "nasal", "orbital")

# name: (mean, standard deviation, loadings on LATENTS); lengths in metres, ratios unitless.
# A feature is mean + std * (sum(loading * latent) + sqrt(1 - sum(loading**2)) * own_noise).
FEATURES: dict[str, tuple[float, float, dict[str, float]]] = {
    "scale": (1.0, 0.035, {"size": 0.9}),
    "width": (1.0, 0.03, {"robustness": 0.3, "adiposity": 0.4}),
    "height": (1.0, 0.025, {"face_length": 0.6}),
    "depth": (1.0, 0.03, {"face_length": 0.3, "size": 0.2}),
    "boxiness": (2.7, 0.15, {"robustness": 0.4}),
    "brow_ridge": (0.005, 0.0018, {"robustness": 0.7, "orbital": 0.3}),
    "brow_y": (0.024, 0.003, {"face_length": 0.3}),
    "eye_y": (0.004, 0.0025, {"face_length": 0.2}),
    "eye_spacing": (0.032, 0.002, {"robustness": 0.3}),
    "eye_depth": (0.011, 0.002, {"orbital": 0.8, "adiposity": -0.3}),
    "nose_length": (0.021, 0.004, {"nasal": 0.7, "robustness": 0.4}),
    "nose_width": (1.0, 0.12, {"robustness": 0.5, "adiposity": 0.3}),
    "nose_bridge": (0.008, 0.0025, {"nasal": 0.6, "orbital": 0.3}),
    "nose_y": (-0.040, 0.004, {"face_length": 0.6}),
    "mouth_y": (-0.068, 0.004, {"face_length": 0.7}),
    "mouth_width": (0.024, 0.002, {"robustness": 0.3}),
    "lips": (0.005, 0.0015, {"adiposity": 0.4}),
    "cheekbones": (0.006, 0.002, {"robustness": 0.4, "orbital": 0.3}),
    "cheeks": (0.004, 0.0025, {"adiposity": 0.8}),
    "jaw_taper": (0.12, 0.04, {"robustness": -0.6, "adiposity": -0.4}),
    "chin": (0.012, 0.004, {"robustness": 0.6}),
    "chin_y": (-0.100, 0.004, {"face_length": 0.8}),
    "ear_size": (1.0, 0.1, {"size": 0.3, "robustness": 0.3}),
    "ear_y": (-0.018, 0.004, {}),
    "ear_protrusion": (0.012, 0.004, {}),
    "occiput": (0.006, 0.003, {"face_length": 0.3}),
}


def icosahedron() -> tuple[np.ndarray, np.ndarray]:
    """Unit icosahedron: vertices (12, 3) and outward-wound faces (20, 3)."""
    phi = (1.0 + 5.0**0.5) / 2.0
    base = np.array([[0.0, s1, s2 * phi] for s1 in (-1, 1) for s2 in (-1, 1)])
    vertices = np.concatenate([np.roll(base, shift, axis=1) for shift in range(3)])
    adjacent = np.isclose(np.linalg.norm(vertices[:, None] - vertices[None], axis=-1), 2.0)
    faces = np.array([corners for corners in itertools.combinations(range(12), 3)
                      if adjacent[np.ix_(corners, corners)].sum() == 6])
    a, b, c = vertices[faces].transpose(1, 0, 2)
    inward = np.einsum("ij,ij->i", np.cross(b - a, c - a), a) < 0
    faces[inward] = faces[inward][:, ::-1]
    return vertices / np.linalg.norm(vertices, axis=1, keepdims=True), faces


def geodesic_sphere(frequency: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere from an icosahedron whose faces are split into ``frequency**2`` triangles.

    Every point is labelled by its exact integer weights on the 12 icosahedron vertices, so
    points shared by neighbouring faces merge without any floating-point tolerance.
    Returns unit vertices (10 f² + 2, 3) and outward-wound faces (20 f², 3).
    """
    corners, ico_faces = icosahedron()
    i, j = np.indices((frequency + 1, frequency + 1)).reshape(2, -1)
    i, j = i[i + j <= frequency], j[i + j <= frequency]
    local = np.full((frequency + 1, frequency + 1), -1)
    local[i, j] = np.arange(i.size)
    weights = np.zeros((len(ico_faces), i.size, 12), dtype=np.int64)
    rows = np.arange(len(ico_faces))[:, None]
    for corner, w in enumerate((frequency - i - j, i, j)):
        weights[rows, np.arange(i.size), ico_faces[:, [corner]]] += w
    labels, vertex_of = np.unique(weights.reshape(-1, 12), axis=0, return_inverse=True)
    vertex_of = vertex_of.reshape(len(ico_faces), i.size)

    up = i + j < frequency
    down = i + j < frequency - 1
    local_tris = np.concatenate([
        np.stack([local[i[up], j[up]], local[i[up] + 1, j[up]], local[i[up], j[up] + 1]], axis=1),
        np.stack([local[i[down] + 1, j[down]], local[i[down] + 1, j[down] + 1],
                  local[i[down], j[down] + 1]], axis=1),
    ])
    faces = np.take_along_axis(vertex_of[:, None, :], local_tris[None], axis=2).reshape(-1, 3)
    points = labels @ corners
    return points / np.linalg.norm(points, axis=1, keepdims=True), faces


def focus_front(u: np.ndarray, k: float) -> np.ndarray:
    """Conformal map of the unit sphere pulling points towards +z (stereographic scale by ``k``)."""
    plus, minus = 1.0 + u[:, 2], k**2 * (1.0 - u[:, 2])
    denominator = plus + minus
    return np.column_stack([2.0 * k * u[:, 0] / denominator, 2.0 * k * u[:, 1] / denominator,
                            (plus - minus) / denominator])


def smoothstep(t: np.ndarray) -> np.ndarray:
    """Quintic ramp from 0 (t <= 0) to 1 (t >= 1) with vanishing first and second derivatives."""
    t = np.clip(t, 0.0, 1.0)
    return t**3 * (10.0 + t * (6.0 * t - 15.0))


def gauss2(a: np.ndarray, b: np.ndarray, ca: float | np.ndarray, cb: float | np.ndarray,
           sa: float | np.ndarray, sb: float | np.ndarray) -> np.ndarray:
    """2-D Gaussian of coordinates ``(a, b)``: centre ``(ca, cb)``, widths ``(sa, sb)``."""
    return np.exp(-0.5 * (((a - ca) / sa) ** 2 + ((b - cb) / sb) ** 2))


def fibonacci_sphere(count: int) -> np.ndarray:
    """``count`` quasi-uniform unit vectors (Fibonacci lattice)."""
    k = np.arange(count) + 0.5
    y = 1.0 - 2.0 * k / count
    azimuth = np.pi * (3.0 - 5.0**0.5) * k
    ring = np.sqrt(1.0 - y**2)
    return np.column_stack([ring * np.cos(azimuth), y, ring * np.sin(azimuth)])


def sample_features(rng: np.random.Generator, count: int) -> dict[str, np.ndarray]:
    """Feature parameters of ``count`` individuals, each as a (count, 1) array."""
    latents = dict(zip(LATENTS, rng.standard_normal((len(LATENTS), count))))
    features = {}
    for name, (mean, std, loadings) in FEATURES.items():
        shared = sum((w * latents[latent] for latent, w in loadings.items()), np.zeros(count))
        own = np.sqrt(1.0 - sum(w * w for w in loadings.values()))
        features[name] = (mean + std * (shared + own * rng.standard_normal(count)))[:, None]
    return features


def skull_radius(u: np.ndarray, f: dict[str, np.ndarray]) -> np.ndarray:
    """Super-ellipsoid skull radius along unit directions ``u``, (S, N)."""
    e = f["boxiness"]
    semi_axes = (0.074, 0.108, 0.097)
    return sum(np.abs(u[:, axis] / s) ** e for axis, s in enumerate(semi_axes)) ** (-1.0 / e)


def face_relief(p: np.ndarray, f: dict[str, np.ndarray]) -> np.ndarray:
    """Outward displacement (S, N) of skull points ``p`` (S, N, 3) that sculpts the head.

    Facial bumps live in the frontal (x, y) projection and fade out behind the face; ears live
    in the lateral (z, y) projection on their own side.
    """
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    front = smoothstep((z - 0.01) / 0.04)
    ax = np.abs(x)
    nose_w = f["nose_width"]
    eye_x, eye_y, nose_y, mouth_y = f["eye_spacing"], f["eye_y"], f["nose_y"], f["mouth_y"]
    face = (
        f["brow_ridge"] * gauss2(ax, y, 0.028, f["brow_y"], 0.022, 0.008)
        - f["eye_depth"] * gauss2(ax, y, eye_x, eye_y, 0.013, 0.010)
        + f["nose_bridge"] * gauss2(x, y, 0.0, 0.5 * (eye_y + nose_y), 0.007 * nose_w, 0.020)
        + f["nose_length"] * gauss2(x, y, 0.0, nose_y, 0.010 * nose_w, 0.010)
        + 0.35 * f["nose_length"] * gauss2(ax, y, 0.014 * nose_w, nose_y - 0.004, 0.007, 0.007)
        + f["cheekbones"] * gauss2(ax, y, 0.046, eye_y - 0.022, 0.014, 0.012)
        + f["cheeks"] * gauss2(ax, y, 0.040, mouth_y + 0.012, 0.018, 0.018)
        + 0.022 * gauss2(x, y, 0.0, mouth_y - 0.015, 0.035, 0.035)
        + f["lips"] * gauss2(x, y, 0.0, mouth_y, f["mouth_width"], 0.007)
        + f["chin"] * gauss2(x, y, 0.0, f["chin_y"], 0.016, 0.012)
    )
    ear_size = f["ear_size"]
    ears = f["ear_protrusion"] * gauss2(z, y, -0.008, f["ear_y"],
                                        0.011 * ear_size, 0.019 * ear_size)
    side = smoothstep((ax - 0.02) / 0.04)
    back = f["occiput"] * gauss2(x, y, 0.0, 0.01, 0.05, 0.04) * smoothstep(-(z + 0.01) / 0.04)
    neck_section = np.exp(-0.5 * ((x / 0.05) ** 2 + ((z + 0.03) / 0.04) ** 2) ** 2)  # flat-topped
    neck = 0.07 * neck_section * smoothstep(-(y + 0.05) / 0.05)
    return face * front + ears * side + back + neck


def random_field(u: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Smooth field (S, N): ``weights`` (S, FIELD_KERNELS) on fixed von Mises-Fisher kernels."""
    centres = fibonacci_sphere(FIELD_KERNELS)
    kernels = np.exp(FIELD_CONCENTRATION * (u @ centres.T - 1.0))
    return weights @ kernels.T


def build_heads(u: np.ndarray, f: dict[str, np.ndarray], field: np.ndarray) -> np.ndarray:
    """Vertices (S, N, 3) of heads with features ``f`` and extra radial offsets ``field`` (S, N)."""
    r0 = skull_radius(u, f)
    radius = r0 + face_relief(r0[..., None] * u, f) + field
    heads = radius[..., None] * u
    heads[..., 0] *= 1.0 - f["jaw_taper"] * smoothstep(-(heads[..., 1] + 0.02) / 0.09)
    ratios = np.stack([f["width"], f["height"], f["depth"]], axis=-1)
    return heads * (f["scale"][..., None] * ratios)


def sample_population(u: np.ndarray, rng: np.random.Generator, count: int) -> np.ndarray:
    """``count`` random heads over the unit directions ``u``, (count, N, 3)."""
    features = sample_features(rng, count)
    weights = FIELD_STD * rng.standard_normal((count, FIELD_KERNELS))
    return build_heads(u, features, random_field(u, weights))


def pca(shapes: np.ndarray, num_modes: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean (N, 3), scaled directions (N, 3, K) and the cumulative variance explained, (K,)."""
    components = principal_components(shapes.reshape(len(shapes), -1), num_modes, randomized=False)
    return (components.mean.reshape(-1, 3), components.scaled_directions.T.reshape(-1, 3, num_modes),
            components.variance_explained())


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted face normals (..., F, 3) of vertices (..., N, 3)."""
    a, b, c = (vertices[..., faces[:, corner], :] for corner in range(3))
    return np.cross(b - a, c - a)


def check_no_flips(shapes: np.ndarray, mean: np.ndarray, faces: np.ndarray) -> None:
    """Raise if any triangle of any shape (S, N, 3) faces the opposite way to the mean's."""
    agreement = np.einsum("sfi,fi->sf", face_normals(shapes, faces), face_normals(mean, faces))
    if (agreement <= 0).any():
        raise RuntimeError(f"{int((agreement <= 0).sum())} flipped triangles in the population")


def landmarks(vertices: np.ndarray) -> dict[str, int]:
    """Named landmark vertices: where rays from the origin to feature points cross the surface."""
    f = {name: mean for name, (mean, _, _) in FEATURES.items()}
    targets = {
        "nose_tip": (0.0, f["nose_y"], 0.11),
        "right_eye": (-f["eye_spacing"], f["eye_y"], 0.09),
        "left_eye": (f["eye_spacing"], f["eye_y"], 0.09),
        "mouth_right": (-f["mouth_width"], f["mouth_y"], 0.09),
        "mouth_left": (f["mouth_width"], f["mouth_y"], 0.09),
        "chin": (0.0, f["chin_y"] - 0.008, 0.08),
        "right_ear": (-0.08, f["ear_y"], -0.008),
        "left_ear": (0.08, f["ear_y"], -0.008),
        "forehead": (0.0, 0.06, 0.09),
        "head_top": (0.0, 0.1, 0.0),
    }
    directions = vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    rays = np.array(list(targets.values()))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    return dict(zip(targets, (directions @ rays.T).argmax(axis=0).tolist()))


def face_region(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Indices of front-facing vertices between forehead and chin, inside the cheeks."""
    normals = np.zeros_like(vertices)
    for corner in range(3):
        np.add.at(normals, faces[:, corner], face_normals(vertices, faces))
    facing = normals[:, 2] > 0.3 * np.linalg.norm(normals, axis=1)
    x, y, z = vertices.T
    inside = (x / 0.065) ** 2 + ((y + 0.025) / 0.1) ** 2 < 1.0
    return np.flatnonzero(inside & facing & (z > 0.03)).astype(np.int32)


def build_model() -> tuple[dict[str, np.ndarray], np.ndarray]:
    """All arrays of the model file, and the cumulative variance explained by the kept modes."""
    sphere, faces = geodesic_sphere(FREQUENCY)
    u = focus_front(sphere, FRONT_FOCUS)
    shapes = sample_population(u, np.random.default_rng(SEED), NUM_SHAPES)
    mean, shapedirs, explained = pca(shapes, NUM_MODES)
    check_no_flips(shapes, mean, faces)
    marks = landmarks(mean)
    arrays = {
        "v_template": mean.astype(np.float32),
        "faces": faces.astype(np.int32),
        "shapedirs": shapedirs.astype(np.float32),
        "landmarks": np.array(list(marks.values()), dtype=np.int32),
        "landmark_names": np.array(list(marks)),
        "region_face": face_region(mean, faces),
    }
    return arrays, explained


def main() -> None:
    """Command-line entry point: build the model and write it to ``--out``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).with_name("default_head.npz"))
    args = parser.parse_args()
    start = time.perf_counter()
    arrays, explained = build_model()
    write_atomic(args.out, npz_bytes(arrays))
    n, _, k = arrays["shapedirs"].shape
    print(f"{n} vertices, {len(arrays['faces'])} faces, {k} modes explaining "
          f"{100 * explained[-1]:.2f}% of the variance "
          f"(first 5: {', '.join(f'{100 * e:.1f}%' for e in explained[:5])})")
    size_mb = args.out.stat().st_size / 1e6
    print(f"wrote {args.out} ({size_mb:.2f} MB) in {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
