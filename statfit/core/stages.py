"""The stage runner: a method is a pipeline of stages, each starting where the last one ended.

A stage is either gradient descent through a parametrisation (:func:`statfit.core.methods.build` and
:func:`statfit.core.fit.run_fit`) or, for ``optimizer="gauss-newton"``, the closed-form coefficient
solve of :mod:`statfit.core.gauss_newton` (objectives with affine residuals only: scan registration).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from statfit.geometry.align import Similarity
from statfit.errors import StatfitError
from statfit.core.fit import Objective, Progress, Snapshot, StageTimer, run_fit
from statfit.core.gauss_newton import fit_coefficients
from statfit.core.methods import build
from statfit.objectives.landmarks import WithLandmarks
from statfit.core.settings import FitSpace, Settings


@dataclass
class Fit:
    """A job's result: fitted vertices (N, 3) in the input's frame and units; ``transform`` maps the
    model's frame onto it (the pre-alignment: scan for register, camera world for render); the
    stages run, the last stage's loss terms, wall seconds (``stage_seconds`` per part of the loop)
    and the iterations run in all; ``pose`` the automatic alignment's report, if one ran; ``threads``
    the CPU threads it ran on; ``fallback``: register's goodness-of-fit test, if one ran (the method
    it falls back to, the fit's ``residual`` and the ``threshold``, in the posed model's RMS radii, and
    whether it was ``used``: then ``stages`` are the fallback's)."""

    vertices: np.ndarray
    transform: Similarity
    stages: tuple[Settings, ...]
    loss: dict[str, float]
    seconds: float
    stage_seconds: dict[str, float] = field(default_factory=dict)
    iterations: int = 0
    pose: dict | None = None
    threads: int = 1
    fallback: dict | None = None


@dataclass
class PipelineResult:
    """vertices (N, 3) in the fit frame, the last stage's loss terms, iterations run in all."""

    vertices: torch.Tensor
    loss: dict[str, float]
    iterations: int


def run_stages(stages: tuple[Settings, ...], space: FitSpace, objective: Objective, x0: torch.Tensor, *,
               on_record: Progress | None = None, on_snapshot: Snapshot | None = None,
               timer: StageTimer | None = None, first_iteration: int = 0) -> PipelineResult:
    """Run ``stages`` in order from vertices ``x0`` (N, 3); the objective's correspondences are
    renewed at the start of every stage. ``first_iteration``: the number of the first (a pipeline
    run a stage at a time, by :mod:`statfit.registration.many`, counts on)."""
    timer = timer or StageTimer()
    x, done, loss = x0, first_iteration, {}
    for settings in stages:
        objective.reset()
        stage_objective = _for_stage(objective, settings)
        if settings.optimizer == "gauss-newton":
            if not hasattr(stage_objective, "jacobian"):
                raise StatfitError("the Gauss–Newton pca stage needs a least-squares objective (scan registration); "
                                   "use the Adam pca stage here")
            with timer("gauss-newton"):
                basis_t, std = space.closed_form_modes()
                result = fit_coefficients(space.mean, basis_t, std, stage_objective, x, settings.iterations,
                                          settings.noise, settings.levels, settings.choose_levels, first_iteration=done,
                                          on_record=on_record,
                                          on_snapshot=on_snapshot)
        else:
            param, optimizer = build(settings, space, x)
            result = run_fit(param, optimizer, stage_objective, settings.iterations, on_record=on_record, timer=timer,
                             first_iteration=done, on_snapshot=on_snapshot)
        x, done, loss = result.vertices, done + result.iterations, result.loss
    return PipelineResult(x, loss, done - first_iteration)


def _for_stage(objective: Objective, settings: Settings) -> Objective:
    """The objective a stage fits: without its landmark term when ``settings.landmarks`` is False."""
    return objective.scan if isinstance(objective, WithLandmarks) and not settings.landmarks else objective
