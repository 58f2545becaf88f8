"""Part 5: `statfit inpaint` on a 1024×1024 RGB texture (3.1 M unknowns): per-step time of hybrid,
statistical and laplacian, the grid Laplacian's build and factorisation, the model-only
reconstruction, and the hole error of each fill.

The model (K modes) is built from 150 generated 128×128 face textures (tests/texture_fixtures.py),
its mean and directions resampled to the benchmark size and orthonormalised by the texture-model
loader: the per-step cost depends only on H·W·C and K, not on where the model came from. The test
texture is a generated face with ``brow_hole``. Per-step time: the median over 10-step windows
(``on_record`` timestamps) after a first window that absorbs first-call costs.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

import sys

from common import FIXTURES, Section, in_child, markdown_table

sys.path.insert(0, str(FIXTURES))

FULL = {"size": 1024, "k": 100, "iterations": 200}
QUICK = {"size": 256, "k": 50, "iterations": 40}
METHODS = ("hybrid", "statistical", "laplacian")


def upsampled_model(size: int, k: int):
    """A texture model of ``size``² from generated 128² faces, resampled."""
    from statfit.texture.model import build_texture_model, texture_model_from_arrays
    from statfit.texture.resample import resize_image
    from texture_fixtures import face_textures

    small = build_texture_model([(str(i), t) for i, t in enumerate(face_textures(150, 128, seed=1))], (128, 128), k)
    arrays = small.npz_arrays()
    mean = resize_image(arrays["v_template"].reshape(128, 128, 3), (size, size)).reshape(-1, 3)
    modes = arrays["shapedirs"].reshape(128, 128, 3, -1)
    shapedirs = np.stack([resize_image(modes[..., j], (size, size)).reshape(-1, 3) for j in range(modes.shape[-1])],
                         axis=-1)
    return texture_model_from_arrays(mean, shapedirs, np.array([size, size]))


def _timed(fn):
    start = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - start


def measure(quick: bool, device: str = "cpu") -> dict:
    """One-off costs and per-method step times and hole errors."""
    from statfit.core.filters import LaplacianFilter
    from statfit.texture.grid import grid_laplacian
    from statfit.texture.inpaint import inpaint, inpaint_settings, model_reconstruction
    from texture_fixtures import brow_hole, face_textures, hole_errors

    config = QUICK if quick else FULL
    size = config["size"]
    model, model_s = _timed(lambda: upsampled_model(size, config["k"]))
    truth, visible = face_textures(1, size, seed=99)[0], brow_hole(size)
    laplacian, grid_s = _timed(lambda: grid_laplacian(size, size))
    _, factor_s = _timed(lambda: LaplacianFilter.from_laplacian(laplacian, 19.0, device=device))
    _, reconstruction_s = _timed(lambda: model_reconstruction(model, truth, visible, device))
    rows = []
    for method in METHODS:
        stamps: list[float] = []
        result, wall = _timed(lambda: inpaint(truth, visible, method, model if method != "laplacian" else None,
                                              settings=inpaint_settings(method, iterations=config["iterations"]),
                                              device=device,
                                              on_record=lambda it, terms: stamps.append(time.perf_counter())))
        windows = np.diff(stamps[:-1]) / 10  # the last record comes at the final iteration, not a window
        rows.append({"method": method, "per_step_ms": 1e3 * float(np.median(windows[1:])), "fit_s": result.seconds,
                     "inpaint_wall_s": wall, **hole_errors(result.result, truth, visible)})
    return {"device": device, "config": config, "k": model.num_modes, "model_build_s": model_s,
            "grid_laplacian_s": grid_s, "factorisation_s": factor_s, "reconstruction_s": reconstruction_s,
            "methods": rows}


def run(quick: bool, device: str, image_dir: Path) -> Section:
    """Measure and format this part."""
    results = in_child("inpainting", "measure", quick, device)  # a fresh process: its own peak memory
    config = results["config"]
    rows = [[r["method"], r["per_step_ms"], r["fit_s"], r["inpaint_wall_s"], r["rmse"], r["correlation"]]
            for r in results["methods"]]
    body = "\n\n".join([
        f"A {config['size']}×{config['size']} RGB texture, a model with K = {results['k']}, the brow hole, "
        f"{config['iterations']} iterations per method. One-off costs: grid Laplacian "
        f"{results['grid_laplacian_s']:.2f} s, factorisation of I + 19L (cholespy) {results['factorisation_s']:.1f} s, "
        f"model-only reconstruction {results['reconstruction_s']:.1f} s; peak RSS {results['peak_rss_mb']:.0f} MB. "
        "Accuracy over many textures and settings: docs/method.md, \"Texture inpainting\".",
        markdown_table(["method", "per step ms", "fit s", "inpaint() wall s", "hole RMSE", "hole corr."], rows),
    ])
    return Section("inpainting", "Texture inpainting speed", body, [], results)
