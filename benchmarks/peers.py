"""Peers on the scan cases: Nicolet et al.'s own ``largesteps`` code against statfit's ``laplacian``
method on the same objective, and three other non-rigid registrations (trimesh's ``nricp_amberg``
and ``nricp_sumner``, pycpd's coherent point drift), template → partial scan.

Every fit runs in a fresh process (``common.in_child``) with the same thread count, in statfit's
unit frame (template centred, unit RMS radius). The adapters take arrays in that frame, so the
tests run them on the embedded model.

    python benchmarks/peers.py [--quick] [--device cpu|cuda] [--json benchmarks/results/peers.json]
"""
from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from typing import Any
from unittest import mock

import numpy as np
import torch

from common import Section, markdown_table, save_json, in_child
from cases import SCAN_CASES, ict_model, relative_errors, scan_case
from statfit.closest import ClosestPointQuery
from statfit.fit import run_fit
from statfit.frame import Frame
from statfit.methods import FitSpace, Settings, build
from statfit.objectives.scan import ScanObjective

THREADS = 2
# (λ, lr, iterations): the paper's laplacian settings and statfit's tuned ones (statfit.methods).
LAPLACIAN = {"paper": (19.0, 0.01, 500), "tuned": (300.0, 0.1, 1000)}
QUICK_ITERATIONS = 200
# trimesh's own default schedules, written out so the report can state them.
AMBERG_STEPS = [[0.01, 10, 0.5, 10], [0.02, 5, 0.5, 10], [0.03, 2.5, 0.5, 10], [0.01, 0, 0.0, 10]]
SUMNER_STEPS = [[1, 0.001, 1.0, 1000, 0], [1, 0.001, 1.0, 1000, 0], [10, 0.001, 1.0, 1000, 0],
                [100, 0.001, 1.0, 1000, 0]]
# Coherent point drift: kernel width β and regularisation α in unit-frame units (chosen on jaw-open,
# see GRID), outlier weight w, and the control vertices that carry the motion field.
CPD = {"alpha": 2.0, "beta": 0.3, "w": 0.1, "controls": 1500, "iterations": 100, "tolerance": 1e-6}


@dataclass
class Fit:
    """Fitted vertices (unit frame) with the set-up (matrix, factorisation) and loop seconds."""

    vertices: np.ndarray
    setup_s: float
    loop_s: float


def scan_objective(faces: np.ndarray, num_vertices: int, points: np.ndarray, device: str) -> ScanObjective:
    """statfit's point-to-surface term (refresh every 10 iterations, 5 % trim) on ``points`` (unit frame)."""
    scan = torch.as_tensor(points, dtype=torch.float32, device=device)
    return ScanObjective(scan, ClosestPointQuery(faces, num_vertices, k=2, device=torch.device(device)))


def statfit_laplacian(template: np.ndarray, faces: np.ndarray, points: np.ndarray, lam: float, lr: float,
                      iterations: int, device: str = "cpu") -> Fit:
    """statfit's laplacian method (x = x0 + (I + λL)⁻¹ u, UniformAdam) through its own fit loop."""
    objective = scan_objective(faces, len(template), points, device)
    x0 = torch.as_tensor(template, dtype=torch.float32, device=device)
    start = time.perf_counter()
    space = FitSpace(x0, torch.empty(0, x0.numel(), device=device), torch.empty(0, device=device), faces)
    param, optimizer = build(Settings("laplacian", iterations, lr, lam=lam), space, x0)
    setup = time.perf_counter() - start
    result = run_fit(param, optimizer, objective, iterations)
    return Fit(result.vertices.cpu().double().numpy(), setup, result.seconds)


class _TorchOn:
    """``torch`` with the device of ``arange`` and ``ones`` forced: largesteps 0.2.2's
    ``compute_matrix`` hard-codes device='cuda', so on the CPU its code runs with this in its place."""

    def __init__(self, device: str):
        self.device = device

    def __getattr__(self, name: str) -> Any:
        attr = getattr(torch, name)
        if name in ("arange", "ones"):
            return lambda *args, **kwargs: attr(*args, **(kwargs | {"device": self.device}))
        return attr


def largesteps_laplacian(template: np.ndarray, faces: np.ndarray, points: np.ndarray, lam: float, lr: float,
                         iterations: int, device: str = "cpu") -> Fit:
    """Nicolet et al.'s loop with their package: M = compute_matrix (I + λL, uniform), u₀ = M x₀,
    x = from_differential(M, u) (Cholesky, differentiable), AdamUniform on u."""
    import largesteps.geometry
    from largesteps.optimize import AdamUniform
    from largesteps.parameterize import from_differential, to_differential

    objective = scan_objective(faces, len(template), points, device)
    x0 = torch.as_tensor(template, dtype=torch.float32, device=device)
    start = time.perf_counter()
    with mock.patch.object(largesteps.geometry, "torch", _TorchOn(device)):
        matrix = largesteps.geometry.compute_matrix(x0, torch.as_tensor(faces, dtype=torch.long, device=device), lam)
    u = to_differential(matrix, x0).requires_grad_(True)
    from_differential(matrix, u.detach())  # factorises (cached per matrix)
    optimizer = AdamUniform([u], lr=lr, betas=(0.9, 0.999))
    setup = time.perf_counter() - start
    start = time.perf_counter()
    for it in range(iterations):
        x = from_differential(matrix, u)
        objective.prepare(x, it)
        loss = objective(x)["data"]
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    loop = time.perf_counter() - start
    return Fit(from_differential(matrix, u).detach().cpu().double().numpy(), setup, loop)


def nricp(template: np.ndarray, faces: np.ndarray, points: np.ndarray, algorithm: str,
          steps: list[list[float]], distance_threshold: float) -> np.ndarray:
    """trimesh's ``nricp_amberg`` or ``nricp_sumner`` of the template onto the point cloud. With a
    point-cloud target the matches come from a k-d tree and target normals are estimated from 8
    neighbours (use_faces / use_vertex_normals only apply to mesh targets)."""
    import trimesh
    from trimesh import registration

    source = trimesh.Trimesh(template, faces, process=False)
    fit = getattr(registration, f"nricp_{algorithm}")
    return np.asarray(fit(source, trimesh.PointCloud(points), steps=steps, distance_threshold=distance_threshold))


def cpd(template: np.ndarray, points: np.ndarray, alpha: float, beta: float, w: float, controls: int,
        iterations: int, tolerance: float) -> np.ndarray:
    """pycpd's DeformableRegistration of ``controls`` random template vertices onto the scan; every
    vertex then moves by CPD's motion field v(z) = Σₖ exp(−|z − yₖ|²/2β²) wₖ. (pycpd 2.0 has no
    low-rank option: its G, diag(P1)·G and solve are dense M×M, O(M³) a step.)"""
    from pycpd import DeformableRegistration

    ids = np.random.default_rng(0).choice(len(template), min(controls, len(template)), replace=False)
    reg = DeformableRegistration(X=points, Y=template[ids], alpha=alpha, beta=beta, w=w,
                                 max_iterations=iterations, tolerance=tolerance)
    reg.register()
    kernel = np.exp(-((template[:, None, :] - template[None, ids, :]) ** 2).sum(-1) / (2 * beta**2))
    return template + kernel @ reg.W


def measure(case_name: str, tool: str, settings: dict[str, Any], device: str = "cpu") -> dict[str, Any]:
    """One fit of ``tool`` on the named scan case (run in a child process): relative errors, wall
    time of the fit and, for the laplacian pair, set-up / per-iteration times and the vertices."""
    from statfit.register import register

    model, case = ict_model(), scan_case(case_name)
    frame = Frame.of(model.template)
    template, points = frame.to_unit(model.template), frame.to_unit(case.points)
    extra: dict[str, Any] = {}
    start = time.perf_counter()
    if tool == "statfit":
        vertices = register(model, case.points, settings["method"], preset=settings["preset"], device=device,
                            iterations=settings.get("iterations")).vertices
    elif tool in ("statfit-laplacian", "largesteps"):
        run = statfit_laplacian if tool == "statfit-laplacian" else largesteps_laplacian
        fit = run(template, model.faces, points, settings["lam"], settings["lr"], settings["iterations"], device)
        vertices = frame.from_unit(fit.vertices)
        extra = {"setup_s": fit.setup_s, "ms_per_iteration": 1e3 * fit.loop_s / settings["iterations"],
                 "unit_vertices": fit.vertices.tolist()}
    elif tool in ("amberg", "sumner"):
        vertices = frame.from_unit(nricp(template, model.faces, points, tool, settings["steps"],
                                         settings["distance_threshold"]))
    elif tool == "cpd":
        vertices = frame.from_unit(cpd(template, points, **settings))
    else:
        raise ValueError(f"unknown tool {tool!r}")
    seconds = time.perf_counter() - start
    return {"case": case_name, "tool": tool, "settings": settings, "seconds": seconds,
            "errors": relative_errors(vertices, case.target, case.observed)} | extra


def template_errors(case_name: str) -> dict[str, float]:
    """The unfitted template's relative errors (the starting point of every tool)."""
    case = scan_case(case_name)
    return relative_errors(ict_model().template, case.target, case.observed)
