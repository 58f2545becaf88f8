"""Non-rigid registration of a model's template to a (partial) scan: the library entry point."""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
import torch

from statfit.align import Similarity, icp, initial_guess
from statfit.closest import ClosestPointQuery
from statfit.errors import StatfitError
from statfit.fit import StageTimer, run_fit
from statfit.frame import Frame
from statfit.methods import FitSpace, Settings, build, resolve
from statfit.model import StatModel
from statfit.objectives.scan import ScanObjective

ALIGNMENTS = ("none", "rigid", "similarity")
# A scan whose extent differs from the model's by more than this factor is taken to be in other units.
UNIT_MISMATCH_FACTOR = 8.0
# Median scan-to-template distance (in model RMS radii) above which the scan is "far" from the model.
FAR_DISTANCE = 0.25


class StatfitWarning(UserWarning):
    """Something the user should know that does not stop the fit."""


@dataclass
class Registration:
    """Fitted vertices (N, 3) in the scan's frame and units, and how they were obtained."""

    vertices: np.ndarray
    transform: Similarity
    stages: tuple[Settings, ...]
    loss: dict[str, float]
    seconds: float
    stage_seconds: dict[str, float] = field(default_factory=dict)


def check_scan(points: np.ndarray, source: str = "scan") -> np.ndarray:
    """Validate an (M, 3) point array: enough points, all finite."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise StatfitError(f"{source}: expected points of shape (M, 3), got {points.shape}")
    if len(points) == 0:
        raise StatfitError(f"{source} has no points")
    if not np.isfinite(points).all():
        raise StatfitError(f"{source} has NaN or infinite coordinates ({int((~np.isfinite(points)).any(axis=1).sum())} points)")
    if len(points) < 10:
        raise StatfitError(f"{source} has only {len(points)} points; need at least 10")
    return points


def resolve_device(device: str) -> torch.device:
    """'auto' picks CUDA when available."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device not in ("cpu", "cuda"):
        raise StatfitError(f"unknown device {device!r}; choose auto, cpu or cuda")
    if device == "cuda" and not torch.cuda.is_available():
        raise StatfitError("--device cuda was asked for but no CUDA device is available")
    return torch.device(device)


def fit_space(model: StatModel, frame: Frame, device: torch.device, dtype: torch.dtype) -> FitSpace:
    """The model's mean, basis and std-devs in the fit frame, as tensors on ``device``."""
    def as_tensor(array: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(array), dtype=dtype, device=device)

    return FitSpace(as_tensor(frame.to_unit(model.template)), as_tensor(model.basis.T),
                    as_tensor(model.std / frame.scale), model.faces)


def prealign(model: StatModel, points: np.ndarray, align: str) -> Similarity:
    """The model→scan transform for ``align`` in none|rigid|similarity; checks units first."""
    if align not in ALIGNMENTS:
        raise StatfitError(f"unknown alignment {align!r}; choose one of {', '.join(ALIGNMENTS)}")
    ratio = np.linalg.norm(np.ptp(points, axis=0)) / np.linalg.norm(np.ptp(model.template, axis=0))
    if align != "similarity" and not 1 / UNIT_MISMATCH_FACTOR < ratio < UNIT_MISMATCH_FACTOR:
        raise StatfitError(f"the scan is {ratio:.3g} times the model's size: are they in different units? "
                           "Rescale one, or use --align similarity")
    if align == "none":
        return Similarity()
    with_scale = align == "similarity"
    start = initial_guess(model.template, points, with_scale)
    if not with_scale and np.linalg.norm(start.translation) < Frame.of(model.template).scale:
        start = Similarity()
    return icp(model.template, model.faces, points, with_scale, start=start)


def register(model: StatModel, points: np.ndarray, method: str = "default", *, preset: str = "tuned",
             align: str = "none", device: str = "cpu", dtype: torch.dtype = torch.float32,
             refresh_every: int = 10, trim: float = 0.05, seed: int = 0,
             on_record: Callable[[int, dict[str, float]], None] | None = None,
             timer: StageTimer | None = None, stages: tuple[Settings, ...] | None = None,
             **overrides: Any) -> Registration:
    """Fit ``model`` to the scan ``points`` (M, 3) with ``method``.

    ``overrides`` (iterations, lr, beta, power, lam, laplacian, solver, mode_gain) replace the
    method's settings; ``stages`` replaces the method altogether by an explicit pipeline. Warns (StatfitWarning) when the scan is far from the model with align='none'.
    """
    points = check_scan(points)
    stages = stages or resolve(method, preset, **overrides)
    torch_device = resolve_device(device)
    torch.manual_seed(seed)
    started = time.perf_counter()
    transform = prealign(model, points, align)
    frame = Frame.of(model.template)
    space = fit_space(model, frame, torch_device, dtype)
    scan = torch.as_tensor(frame.to_unit(transform.inverse_apply(points)), dtype=dtype, device=torch_device)
    objective = ScanObjective(scan, ClosestPointQuery(model.faces, model.num_vertices, k=2, device=torch_device),
                              refresh_every=refresh_every, trim=trim)
    median = float(objective.refresh(space.mean).distance.median())
    if align == "none" and median > FAR_DISTANCE:
        warnings.warn(f"the scan is far from the model (median distance {median * frame.scale:.3g}, "
                      f"{median:.2f} model radii); consider --align rigid", StatfitWarning, stacklevel=2)
    timer = timer or StageTimer(sync=torch_device.type == "cuda")
    x, done, loss = space.mean.clone(), 0, {}
    for settings in stages:
        param, optimizer = build(settings, space, x)
        objective.reset()  # a new stage starts from fresh correspondences
        result = run_fit(param, optimizer, objective, settings.iterations, on_record=on_record,
                         timer=timer, first_iteration=done)
        x, done, loss = result.vertices, done + settings.iterations, result.loss
    vertices = transform.apply(frame.from_unit(x.detach().cpu().double().numpy()))
    return Registration(vertices, transform, stages, loss, time.perf_counter() - started, dict(timer.seconds))
