"""Many scans registered with one model in one program: the fits' gradient stages stepped together.

:func:`register_many` fits each scan as :func:`statfit.registration.job.register` would: its own
pose search, its own closed-form stage (Gauss–Newton stops when that fit has converged), its own
fallback test. The gradient stages of all the fits run as one: vertices (B, N, 3), one filter
product for all B (:mod:`statfit.core.filters`), UniformAdam with each fit's own step scale, one
data term (:class:`statfit.objectives.scans.ScanBatch`). So a fitting iteration launches the ops
of one fit, whatever B: on a GPU, where a register iteration is launch-bound, B fits cost about
what one does; the fits whose fallback fires are refitted together too.

What differs from B calls of ``register``: every fit of a batch renews its correspondences at the
same iterations, every ``refresh_every`` counted from the gradient stage's start (alone, a fit
counts on from where its closed-form stage stopped); each fit's recorded loss is its terms at its
final vertices. Fits agree with ``register``'s to float rounding otherwise (docs/benchmarks.md §15).
A fit that fails (a scan refused, a pose not found, a divergence) fails alone: a batched stage that
diverges is rerun a fit at a time.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import numpy as np
import torch

from statfit.core.methods import Fallback, resolve
from statfit.core.settings import Settings
from statfit.core.stages import Fit, PipelineResult
from statfit.core.threads import intra_op_threads, task_threads
from statfit.core.together import FitOutcome, Member, each_alone, fits_in_memory, run_stages_together
from statfit.errors import StatfitError
from statfit.model.cut import fitting_model
from statfit.model.statmodel import StatModel
from statfit.objectives.scans import ScanBatch
from statfit.registration.posed import FitSetup, PosedScan, model_tensors, plan_fits
from statfit.structures.scan import MESH_SAMPLES, THIN_ABOVE, Scan, sample_size

def together_for(model: StatModel, device: torch.device) -> int:
    """How many scans a batch worker registers together by default: 1 on a CPU, where fits step
    together gain only what the filter's products share (docs/benchmarks.md §15) and give other
    bytes than ``statfit register``; on a GPU as many as fit its memory
    (:func:`statfit.core.together.fits_in_memory` of :func:`bytes_per_fit`)."""
    return fits_in_memory(bytes_per_fit(model), device) if device.type == "cuda" else 1


def bytes_per_fit(model: StatModel) -> int:
    """A generous bound on one fit's memory in a stage stepped together (float32): 40 copies of its
    vertices (parameters, moments, gradients, filter products) and 6 KB per scan point (its ~12
    candidate triangles' planes and products at a refresh, the attachment, the masks), for the most
    points a fit is given (a denser scan is thinned: :meth:`statfit.structures.scan.Scan.thinned`).
    Measured on a CPU, host and device together: 27 MB a fit for ICT's head and 4,300 points (16
    fits at once against one: 860 against 458 MB at the peak), ~5 KB a point."""
    points = max(THIN_ABOVE * sample_size(model.num_vertices), MESH_SAMPLES[1])
    return 4 * 40 * 3 * model.num_vertices + 6000 * points


class _Scan(Member):
    """A scan's fit in a batch: besides a member's, its posed scan, the current pipeline's set-up and
    the last pipeline's result (posed._StagesRun)."""

    def __init__(self, index: int):
        super().__init__(index)
        self.posed: PosedScan | None = None
        self.setup: FitSetup | None = None
        self.run = None


def register_many(model: StatModel, scans: Sequence[np.ndarray | Scan], method: str = "default", *,
                  landmarks: Sequence[np.ndarray | None] | None = None, preset: str = "tuned", align: str = "auto",
                  device: str | None = None, dtype: torch.dtype = torch.float32, refresh_every: int = 10,
                  trim: float = 0.05, seed: int = 0, stages: tuple[Settings, ...] | None = None,
                  region: str | None = None, threads: int | None = None, landmark_weight: float | None = None,
                  clutter: bool | None = None, fallback: Fallback | bool | None = True, rigid_modes: str = "auto",
                  **overrides: Any) -> list[FitOutcome]:
    """Fit ``model`` to each of ``scans`` ((M_b, 3) points or :class:`Scan`), with ``landmarks`` (one
    (L, 3) array or None per scan) and the options of :func:`statfit.registration.job.register`, the
    gradient stages of all the fits stepped together. One :class:`statfit.core.together.FitOutcome` per scan, in order; a bad
    option raises StatfitError (it would fail every fit)."""
    if landmarks is not None and len(landmarks) != len(scans):
        raise StatfitError(f"{len(scans)} scans but {len(landmarks)} landmark sets")
    marked = landmarks is not None and any(each is not None for each in landmarks)
    model = fitting_model(model, rigid_modes, finds_pose=align != "none" or marked)
    plan = plan_fits(model, method, preset, stages, overrides, trim, refresh_every, landmark_weight, fallback, device,
                     threads)
    members = [_Scan(i) for i in range(len(scans))]
    with intra_op_threads(plan.threads):
        torch.manual_seed(seed)
        shared = model_tensors(model, plan, dtype)
        # Each fit's host work (its pose search, set-up, closed-form stage and fallback test) runs side
        # by side with the others' where one fit would leave cores idle: the same fits as one after another.
        side_by_side = task_threads(len(members), plan.threads_asked)
        each = plan if side_by_side == 1 else dataclasses.replace(plan, threads_asked=1)    # a search on its thread

        def pose(member: _Scan) -> PosedScan:
            marks = None if landmarks is None else landmarks[member.index]
            return PosedScan.of(model, scans[member.index], each, align, marks, clutter, region, seed, dtype, shared)

        for member, posed_scan in zip(members, each_alone(members, pose, side_by_side)):
            member.posed = posed_scan
        posed = [m for m in members if not m.failed]
        _fit_together(posed, plan.stages, plan.weight, side_by_side, warn_far=align == "none")
        reports: dict[int, dict] = {}
        if plan.fallback is not None:
            tested = [m for m in posed if not m.failed and m.run.whole_model]

            def fallback_test(member: _Scan) -> dict:
                with member.timer("fallback test"):
                    return member.posed.fallback_test(member.run, plan.fallback)

            reports = dict(zip((m.index for m in tested), each_alone(tested, fallback_test, side_by_side)))
            refit = [m for m in posed if not m.failed and (reports.get(m.index) or {}).get("used")]
            first = {m.index: m.run.result.iterations for m in refit}      # the refit's iterations add to these
            _fit_together(refit, resolve(plan.fallback.method), plan.fallback_weight, side_by_side, warn_far=False)
            for member in refit:
                member.run.result.iterations += first[member.index]
        for member in posed:
            if member.failed:
                continue
            used = (reports.get(member.index) or {}).get("used")
            result = member.run.result
            member.outcome.fit = Fit(member.posed.to_scan_frame(result.vertices), member.posed.transform,
                                     resolve(plan.fallback.method) if used else plan.stages, result.loss,
                                     member.seconds, dict(member.timer.seconds), result.iterations, member.run.pose,
                                     plan.threads, reports.get(member.index))
    return [m.outcome for m in members]


def _fit_together(members: list[_Scan], stages: tuple[Settings, ...], weight: float, side_by_side: int,
                  warn_far: bool) -> None:
    """Run ``stages`` on every member (its ``run`` holds the result): each fit's set-up (its start,
    hair test and data term), closed-form and unbatchable stages a fit at a time, ``side_by_side`` of
    them at once, gradient stages of filtered methods together."""
    setups = each_alone(members, lambda member: member.posed.setup(stages, weight, warn_far), side_by_side)
    for member, setup in zip(members, setups):
        member.setup = setup
        if member.setup is not None:
            member.space, member.objective = member.posed.space, member.setup.objective
            member.x, member.done, member.loss = member.setup.start, 0, {}
    run_stages_together(members, stages, _scan_batch, side_by_side)
    for member in members:
        if not member.failed:
            member.run = member.alone(member.setup.ran, PipelineResult(member.x, member.loss, member.done))


def _scan_batch(members: list[_Scan], settings: Settings) -> ScanBatch:
    """The data term of ``members`` stepped together in a stage of ``settings``."""
    return ScanBatch([m.setup.scan for m in members], [m.setup.landmarks for m in members]
                     ).with_landmarks(settings.landmarks)
