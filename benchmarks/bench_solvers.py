"""Prefactored sparse solvers for the Laplacian filter (I + λL)⁻¹: factorisation and solve times.

Meshes: the ICT head (11,248 vertices) and triangulated grids; 3 right-hand sides (x, y, z), float32
torch tensors in and out as the filter uses them. Also the statistical filter's time for reference.

    python benchmarks/bench_solvers.py [--threads 2]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from statfit.filters import StatisticalFilter
from statfit.laplacian import smoothing_matrix
from statfit.solvers import SOLVERS, make_solver

ICT = Path(__file__).resolve().parents[2] / "shared" / "data" / "ict-face" / "ict_face_identity.npz"


def grid(side: int) -> tuple[np.ndarray, np.ndarray]:
    """A side × side triangulated grid: vertices (side², 3), faces (2(side−1)², 3)."""
    i, j = np.meshgrid(np.arange(side), np.arange(side), indexing="ij")
    vertices = np.stack([i.ravel(), j.ravel(), np.zeros(side * side)], axis=1) / side
    idx = (i * side + j)[:-1, :-1].ravel()
    faces = np.concatenate([np.stack([idx, idx + side, idx + 1], 1), np.stack([idx + 1, idx + side, idx + side + 1], 1)])
    return vertices, faces


def median_ms(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    meshes = {"grid 128²": grid(128), "grid 256²": grid(256)}
    if ICT.is_file():
        with np.load(ICT) as data:
            meshes = {"ICT head": (data["v_template"].astype(np.float64), data["faces"])} | meshes
    print("| mesh | vertices | solver | factorise ms | solve ms (3 rhs) | statistical filter ms (k=100) |")
    print("|---|---|---|---|---|---|")
    rng = np.random.default_rng(0)
    for name, (vertices, faces) in meshes.items():
        matrix = smoothing_matrix(vertices, faces, 19.0)
        rhs = torch.as_tensor(rng.standard_normal((len(vertices), 3)), dtype=torch.float32)
        basis_t = torch.linalg.qr(torch.randn(3 * len(vertices), 100))[0].t().contiguous()
        statistical = median_ms(lambda: StatisticalFilter(basis_t, 30.0)(rhs), 50)
        for solver in SOLVERS:
            factorise = median_ms(lambda: make_solver(matrix, solver), 3)
            prepared = make_solver(matrix, solver)
            solve = median_ms(lambda: prepared.solve(rhs), 50)
            print(f"| {name} | {len(vertices)} | {solver} | {factorise:.1f} | {solve:.2f} | {statistical:.2f} |")


if __name__ == "__main__":
    main()
