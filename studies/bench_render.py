"""Benchmark of one differentiable render step of the ICT head (statfit.renderer).

One step: rasterize → vertex normals + interpolation → antialias (normals and mask) → a loss
→ backward to the vertices. Prints the median time per stage and of the whole step, and the
median of the same step through ``render_normals`` as a cross-check.

    PYTHONPATH=. python studies/bench_render.py [--size 512] [--iters 50] [--threads 1]

``--tuned-malloc`` raises glibc's mmap/trim thresholds first (as MALLOC_MMAP_THRESHOLD_ and
MALLOC_TRIM_THRESHOLD_ would): torch's CPU tensors of a few MB are otherwise mmap'd fresh on every
allocation, and their page faults are a large part of the step on some machines.
"""
from __future__ import annotations

import argparse
import ctypes
import sys
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from statfit.renderer import Camera, MeshAdjacency, normal_image, rasterize, render_normals, silhouette_crossings

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from common import ICT_MODEL as ICT  # noqa: E402
STAGES = ("rasterize", "normal image", "antialias", "loss", "backward")


def tune_malloc() -> None:
    """Keep freed memory in the heap (glibc only): mmap threshold 32 MiB, trim threshold 1 GiB."""
    libc = ctypes.CDLL("libc.so.6")
    m_trim_threshold, m_mmap_threshold = -1, -3
    libc.mallopt(m_mmap_threshold, 32 << 20)
    libc.mallopt(m_trim_threshold, 1 << 30)


def staged_step(vertices: torch.Tensor, faces: torch.Tensor, camera: Camera, adjacency: MeshAdjacency,
                target: torch.Tensor, sync: Callable[[], None]) -> list[float]:
    """One step with a timestamp after each stage; the same computation as :func:`render_normals`."""
    marks = [time.perf_counter()]

    def mark() -> None:
        sync()
        marks.append(time.perf_counter())

    fragments = rasterize(vertices, faces, camera)
    mark()
    normals = normal_image(vertices, faces, fragments, camera)
    mark()
    crossings = silhouette_crossings(fragments, faces, adjacency)
    normal_map, mask = crossings.blend(normals), crossings.blend(fragments.coverage())[..., 0]
    mark()
    loss = loss_of(normal_map, mask, target)
    mark()
    loss.backward()
    mark()
    return list(np.diff(marks))


def loss_of(normal_map: torch.Tensor, mask: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Squared error of the normal map (H, W, 3) and mask (H, W) against target (H, W, 4)."""
    return (torch.nn.functional.mse_loss(normal_map, target[..., :3], reduction="sum")
            + torch.nn.functional.mse_loss(mask, target[..., 3], reduction="sum"))


def whole_step(vertices: torch.Tensor, faces: torch.Tensor, camera: Camera, adjacency: MeshAdjacency,
               target: torch.Tensor, sync: Callable[[], None]) -> float:
    start = time.perf_counter()
    normal_map, mask = render_normals(vertices, faces, camera, adjacency=adjacency)
    loss_of(normal_map, mask, target).backward()
    sync()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--iters", type=int, default=50)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--tuned-malloc", action="store_true")
    args = parser.parse_args()
    if args.tuned_malloc:
        tune_malloc()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    with np.load(ICT) as data:
        template, faces_np = data["v_template"], data["faces"]
    vertices = torch.tensor(template, dtype=torch.float32, device=device).requires_grad_()
    faces = torch.tensor(faces_np, dtype=torch.long, device=device)
    camera = Camera.look_at([0.0, -2.4, 60.0], [0.0, -2.4, 0.0], [0.0, 1.0, 0.0], 38.0, args.size, args.size)
    adjacency = MeshAdjacency.from_faces(faces)
    target = torch.rand(args.size, args.size, 4, generator=torch.Generator().manual_seed(0)).to(device)

    def timed(step):
        def run():
            vertices.grad = None
            sync()
            return step(vertices, faces, camera, adjacency, target, sync)
        return run

    staged, whole = timed(staged_step), timed(whole_step)
    for _ in range(args.warmup):
        staged()
        whole()
    stage_times, whole_times = [], []
    for _ in range(args.iters):  # interleaved, so both see the same machine load
        stage_times.append(staged())
        whole_times.append(whole())
    stage_ms = np.array(stage_times) * 1e3
    fragments = rasterize(vertices.detach(), faces, camera)
    print(f"ICT head: {len(template)} vertices, {len(faces_np)} triangles; {args.size}×{args.size}, "
          f"{len(fragments.pixel)} covered pixels; {args.threads} thread(s), {device}, float32"
          + (", tuned malloc" if args.tuned_malloc else "")
          + f"; load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    print(f"{'stage':<24}{'median ms':>10}{'p10':>8}{'p90':>8}")
    for name, column in zip(STAGES, stage_ms.T):
        print(f"{name:<24}{np.median(column):>10.2f}{np.percentile(column, 10):>8.2f}{np.percentile(column, 90):>8.2f}")
    total = stage_ms.sum(axis=1)
    print(f"{'step (sum of stages)':<24}{np.median(total):>10.2f}{np.percentile(total, 10):>8.2f}"
          f"{np.percentile(total, 90):>8.2f}")
    whole_ms = np.array(whole_times) * 1e3
    print(f"{'step (render_normals)':<24}{np.median(whole_ms):>10.2f}{np.percentile(whole_ms, 10):>8.2f}"
          f"{np.percentile(whole_ms, 90):>8.2f}")


if __name__ == "__main__":
    main()
