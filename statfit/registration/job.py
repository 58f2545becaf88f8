"""Non-rigid registration of a model's template to a (partial) scan: the library entry point."""
from __future__ import annotations

import time
from typing import Any, Callable

import numpy as np
import torch

from statfit.core.fit import StageTimer
from statfit.core.methods import Fallback, resolve
from statfit.core.settings import Settings
from statfit.core.stages import Fit
from statfit.core.threads import intra_op_threads
from statfit.model.cut import fitting_model
from statfit.model.statmodel import StatModel
from statfit.registration.posed import PosedScan, plan_fits
from statfit.structures.scan import Scan


def register(model: StatModel, points: np.ndarray | Scan, method: str = "default", *, preset: str = "tuned",
             align: str = "auto", device: str | None = None, dtype: torch.dtype = torch.float32,
             refresh_every: int = 10, trim: float = 0.05, seed: int = 0,
             on_record: Callable[[int, dict[str, float]], None] | None = None,
             timer: StageTimer | None = None, stages: tuple[Settings, ...] | None = None,
             region: str | None = None, landmarks: np.ndarray | None = None,
             on_snapshot: Callable[[int, np.ndarray], None] | None = None, threads: int | None = None,
             landmark_weight: float | None = None, clutter: bool | None = None,
             fallback: Fallback | bool | None = True, rigid_modes: str = "auto", **overrides: Any) -> Fit:
    """Fit ``model`` to the scan ``points`` (M, 3), or a :class:`statfit.structures.scan.Scan` (e.g. drawn
    from a mesh scan by area), with ``method``.

    ``align``: ``auto`` finds the scan's pose, scale and power-of-ten units without landmarks and
    leaves a scan that already lies on the model where it is (:mod:`statfit.registration.pose.search`; its
    report is the result's ``pose``); ``none`` takes the scan as lying in the model's frame;
    ``rigid``/``similarity``: ICP from the centroids.

    ``region`` names a stored vertex subset: only scan points whose closest surface point lies on
    the region's triangles enter the data term, while the filter and prior still move every vertex.
    ``landmarks`` (L, 3), the scan's points for the model's landmarks (NaN = missing), pre-align the
    scan by a similarity first (refined by ICP when ``align`` is rigid or similarity), then stay a
    fit term of ``landmark_weight`` (0: the start only; None: the method's,
    :func:`statfit.core.methods.landmark_weight`; :mod:`statfit.objectives.landmarks`).
    ``clutter`` turns on the data term's rules for points off the template (normals, robust
    distance; :mod:`statfit.objectives.scan`) and, without a ``region``, leaves out the points a fit
    of the model's face alone finds to be hair and those nearest its scalp (:mod:`statfit.registration.hair`:
    hair passes every rule), or keeps the data term to the face (:func:`face_triangles`) when most
    of the scan is out there;
    ``None``: on when the automatic alignment found more than 1 − CLUTTER_MATCHED of the points
    unexplained by its fit with every mode.
    ``on_snapshot(iteration, vertices)`` receives the current vertices (N, 3), in the scan's frame,
    every 10 iterations (e.g. to trace the error against a ground truth). ``threads``: torch
    intra-op threads for the fit (default: chosen from the model's size, :mod:`statfit.core.threads`).

    ``overrides`` (iterations, lr, beta, power, lam, laplacian, solver, mode_gain) replace the
    method's settings; ``stages`` replaces the method altogether by an explicit pipeline.
    ``fallback``: True, the method's own (:func:`statfit.core.methods.fallback`: the default
    pipeline's, unless ``stages`` or ``overrides`` are given); a :class:`Fallback`; False or None: none.
    Where the fit leaves the scan points it was given farther than the fallback's residual from its
    surface on average, or its shape's code in the model is larger than the fallback's (RMS over the
    modes, standard deviations), the fallback's method refits from the same pose and its fit is
    returned (a StatfitWarning says so; the result's ``fallback`` reports both either way). The points
    are those the data term was given (the hair left out); it does not apply where the data term
    keeps to a region (``region``, or the face alone under hair): there the residual measures what
    the fit leaves out by design. Warns (StatfitWarning) when the scan is far from the model with align='none'.
    ``rigid_modes``: fit the model's modes as given or without their rigid motion
    (:func:`statfit.model.cut.fitting_model`; ``auto``: without it where it is most of what they do
    and the pose is found, by ``align`` or ``landmarks``).
    """
    model = fitting_model(model, rigid_modes, finds_pose=align != "none" or landmarks is not None)
    plan = plan_fits(model, method, preset, stages, overrides, trim, refresh_every, landmark_weight, fallback,
                     device, threads)
    with intra_op_threads(plan.threads):
        torch.manual_seed(seed)
        started = time.perf_counter()
        posed = PosedScan.of(model, points, plan, align, landmarks, clutter, region, seed, dtype)
        timer = timer or StageTimer.for_device(plan.device)
        fit = posed.fit(plan.stages, plan.weight, timer, on_record, on_snapshot, warn_far=align == "none")
        stages, report = plan.stages, None
        if plan.fallback and fit.whole_model:
            with timer("fallback test"):
                report = posed.fallback_test(fit, plan.fallback)
            if report["used"]:
                stages = resolve(plan.fallback.method)
                first = fit.result.iterations
                fit = posed.fit(stages, plan.fallback_weight, timer, _counting_on(on_record, first),
                                _counting_on(on_snapshot, first), warn_far=False)
                fit.result.iterations += first
        return Fit(posed.to_scan_frame(fit.result.vertices), posed.transform, stages, fit.result.loss,
                   time.perf_counter() - started, dict(timer.seconds), fit.result.iterations, fit.pose, plan.threads,
                   report)


def _counting_on(callback: Callable[..., None] | None, first: int) -> Callable[..., None] | None:
    """``callback(iteration, ...)`` with the iterations numbered on from ``first`` (a refit's records
    follow the first fit's in a log, as its iterations are summed)."""
    return None if callback is None else lambda iteration, *rest: callback(first + iteration, *rest)
