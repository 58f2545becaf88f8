"""Speed of `statfit inpaint` on a 1024×1024 RGB texture: per-step time of hybrid, statistical and
laplacian, the grid Laplacian's build and factorisation, and the model-only reconstruction.

The model (K modes) is built from 150 generated 128×128 face textures (statfit.texture.synthetic)
and its mean and directions resampled to 1024×1024, then orthonormalised by the texture-model
loader: the per-step cost depends only on H·W·C and K, not on where the model came from. The test
texture is a generated 1024×1024 face with ``brow_hole``. Per-step time: the median over 10-step
windows (``on_record`` timestamps) after a first window that absorbs first-call costs. Prints a
Markdown table; ``--json PATH`` also saves the numbers.

    OMP_NUM_THREADS=2 PYTHONPATH=. python benchmarks/bench_inpaint.py [--k 100] [--iterations 200] [--threads 2]
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch

from statfit.filters import LaplacianFilter
from statfit.texture.grid import grid_laplacian
from statfit.texture.inpaint import inpaint, inpaint_settings, model_reconstruction
from statfit.texture.metrics import hole_errors
from statfit.texture.model import build_texture_model, texture_model_from_arrays
from statfit.texture.resample import resize_image
from statfit.texture.synthetic import brow_hole, face_textures

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_register import machine  # noqa: E402

SIZE = 1024


def upsampled_model(k: int):
    small = build_texture_model([(str(i), t) for i, t in enumerate(face_textures(150, 128, seed=1))], (128, 128), k)
    arrays = small.npz_arrays()
    mean = resize_image(arrays["v_template"].reshape(128, 128, 3), (SIZE, SIZE)).reshape(-1, 3)
    modes = arrays["shapedirs"].reshape(128, 128, 3, -1)
    shapedirs = np.stack([resize_image(modes[..., j], (SIZE, SIZE)).reshape(-1, 3) for j in range(modes.shape[-1])],
                         axis=-1)
    return texture_model_from_arrays(mean, shapedirs, np.array([SIZE, SIZE]))


def timed(fn):
    start = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--k", type=int, default=100)
    parser.add_argument("--iterations", type=int, default=200)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    model, model_s = timed(lambda: upsampled_model(args.k))
    truth, visible = face_textures(1, SIZE, seed=99)[0], brow_hole(SIZE)
    laplacian, grid_s = timed(lambda: grid_laplacian(SIZE, SIZE))
    _, factor_s = timed(lambda: LaplacianFilter.from_laplacian(laplacian, 19.0))
    _, reconstruction_s = timed(lambda: model_reconstruction(model, truth, visible))
    rows = []
    for method in ("hybrid", "statistical", "laplacian"):
        stamps: list[float] = []
        result, wall = timed(lambda: inpaint(truth, visible, method, model if method != "laplacian" else None,
                                             settings=inpaint_settings(method, iterations=args.iterations),
                                             on_record=lambda it, terms: stamps.append(time.perf_counter())))
        windows = np.diff(stamps[:-1]) / 10          # the last record comes at the final iteration, not a window
        rows.append({"method": method, "iterations": args.iterations,
                     "per_step_ms": 1e3 * float(np.median(windows[1:])), "fit_s": result.seconds,
                     "inpaint_wall_s": wall, **hole_errors(result.result, truth, visible)})
    report = {"size": [SIZE, SIZE, 3], "k": model.num_modes, "threads": args.threads, "machine": machine(),
              "model_build_s": model_s, "grid_laplacian_s": grid_s, "factorisation_s": factor_s,
              "reconstruction_s": reconstruction_s, "methods": rows,
              "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}
    print(f"1024×1024×3, K = {model.num_modes}, {args.threads} threads; grid Laplacian {grid_s:.2f} s, "
          f"factorisation (λ = 19) {factor_s:.2f} s, model-only reconstruction {reconstruction_s:.2f} s, "
          f"peak RSS {report['peak_rss_mb']:.0f} MB\n")
    print("| method | per step ms | fit s | inpaint() wall s | hole RMSE | hole corr. |\n|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['method']} | {r['per_step_ms']:.0f} | {r['fit_s']:.1f} | {r['inpaint_wall_s']:.1f} | "
              f"{r['rmse']:.4f} | {r['correlation']:.3f} |")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
