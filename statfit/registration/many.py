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

import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import torch

from statfit.core.fit import StageTimer, run_fit
from statfit.core.methods import Fallback, batchable, build, resolve
from statfit.core.settings import Settings
from statfit.core.stages import Fit, PipelineResult, run_stages
from statfit.core.threads import intra_op_threads
from statfit.errors import StatfitError, one_line
from statfit.model.statmodel import StatModel
from statfit.objectives.scans import ScanBatch
from statfit.registration.posed import FitSetup, PosedScan, model_tensors, plan_fits
from statfit.structures.scan import MESH_SAMPLES, THIN_ABOVE, Scan, sample_size

# The most fits a worker steps together by default on a GPU (issue 38's batch of 64).
MOST_TOGETHER = 64


def together_for(model: StatModel, device: torch.device) -> int:
    """How many scans a batch worker registers together by default: 1 on a CPU, where fits step
    together gain only what the filter's products share (docs/benchmarks.md §15) and give other
    bytes than ``statfit register``; on a GPU, where an iteration costs its launches whatever B, as
    many as :func:`bytes_per_fit` fits in a quarter of the card's free memory, at most MOST_TOGETHER."""
    if device.type != "cuda":
        return 1
    free, _ = torch.cuda.mem_get_info(device)
    return int(max(1, min(MOST_TOGETHER, free // 4 // bytes_per_fit(model))))


def bytes_per_fit(model: StatModel) -> int:
    """A generous bound on one fit's memory in a stage stepped together (float32): 40 copies of its
    vertices (parameters, moments, gradients, filter products) and 6 KB per scan point (its ~12
    candidate triangles' planes and products at a refresh, the attachment, the masks), for the most
    points a fit is given (a denser scan is thinned: :meth:`statfit.structures.scan.Scan.thinned`).
    Measured on a CPU, host and device together: 27 MB a fit for ICT's head and 4,300 points (16
    fits at once against one: 860 against 458 MB at the peak), ~5 KB a point."""
    points = max(THIN_ABOVE * sample_size(model.num_vertices), MESH_SAMPLES[1])
    return 4 * 40 * 3 * model.num_vertices + 6000 * points


@dataclass
class ScanFit:
    """One scan's outcome in :func:`register_many`: its ``fit``, or the one-line ``error`` that
    stopped it; the ``warnings`` it raised, in order."""

    fit: Fit | None = None
    error: str | None = None
    warnings: list[str] = field(default_factory=list)


class _Member:
    """A scan's fit in a batch: its posed scan, the current pipeline's set-up and vertices, its own
    timer and clock, what it raised."""

    def __init__(self, index: int):
        self.index = index
        self.outcome = ScanFit()
        self.timer = StageTimer()
        self.seconds = 0.0
        self.posed: PosedScan | None = None
        self.setup: FitSetup | None = None
        self.x: torch.Tensor | None = None
        self.done = 0
        self.loss: dict[str, float] = {}
        self.run = None     # the last pipeline's result (posed._StagesRun)

    @property
    def failed(self) -> bool:
        return self.outcome.error is not None

    def alone(self, work, *args):
        """``work(*args)`` on this fit's account: its time, its warnings; a failure becomes its error
        (and None is returned)."""
        started = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                return work(*args)
            except Exception as error:  # noqa: BLE001 - a bug or an unforeseen input: this fit's, the others go on
                self.outcome.error = one_line(error)
            finally:
                self.outcome.warnings += [str(w.message) for w in caught]
                self.seconds += time.perf_counter() - started
        return None


def register_many(model: StatModel, scans: Sequence[np.ndarray | Scan], method: str = "default", *,
                  landmarks: Sequence[np.ndarray | None] | None = None, preset: str = "tuned", align: str = "auto",
                  device: str | None = None, dtype: torch.dtype = torch.float32, refresh_every: int = 10,
                  trim: float = 0.05, seed: int = 0, stages: tuple[Settings, ...] | None = None,
                  region: str | None = None, threads: int | None = None, landmark_weight: float | None = None,
                  clutter: bool | None = None, fallback: Fallback | bool | None = True, **overrides: Any
                  ) -> list[ScanFit]:
    """Fit ``model`` to each of ``scans`` ((M_b, 3) points or :class:`Scan`), with ``landmarks`` (one
    (L, 3) array or None per scan) and the options of :func:`statfit.registration.job.register`, the
    gradient stages of all the fits stepped together. One :class:`ScanFit` per scan, in order; a bad
    option raises StatfitError (it would fail every fit)."""
    if landmarks is not None and len(landmarks) != len(scans):
        raise StatfitError(f"{len(scans)} scans but {len(landmarks)} landmark sets")
    plan = plan_fits(model, method, preset, stages, overrides, trim, refresh_every, landmark_weight, fallback, device,
                     threads)
    members = [_Member(i) for i in range(len(scans))]
    with intra_op_threads(plan.threads):
        torch.manual_seed(seed)
        shared = model_tensors(model, plan.device, dtype)
        for member, scan in zip(members, scans):
            marks = None if landmarks is None else landmarks[member.index]
            member.posed = member.alone(PosedScan.of, model, scan, plan, align, marks, clutter, region, seed, dtype,
                                        shared)
        posed = [m for m in members if not m.failed]
        _fit_together(posed, plan.stages, plan.weight, warn_far=align == "none")
        reports: dict[int, dict] = {}
        if plan.fallback is not None:
            for member in posed:
                if not member.failed and member.run.whole_model:
                    with member.timer("fallback test"):
                        reports[member.index] = member.alone(member.posed.fallback_test, member.run, plan.fallback)
            refit = [m for m in posed if not m.failed and (reports.get(m.index) or {}).get("used")]
            first = {m.index: m.run.result.iterations for m in refit}      # the refit's iterations add to these
            _fit_together(refit, resolve(plan.fallback.method), plan.fallback_weight, warn_far=False)
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


def _fit_together(members: list[_Member], stages: tuple[Settings, ...], weight: float, warn_far: bool) -> None:
    """Run ``stages`` on every member (its ``run`` holds the result): closed-form and unbatchable
    stages a fit at a time, gradient stages of filtered methods together; a failed batched stage
    is rerun a fit at a time, so that only the fits that fail alone fail."""
    for member in members:
        member.setup = member.alone(member.posed.setup, stages, weight, warn_far)
        if member.setup is not None:
            member.x, member.done, member.loss = member.setup.start, 0, {}
    live = [m for m in members if not m.failed]
    for settings in stages:
        if len(live) > 1 and batchable(settings):
            if not _stage_together(live, settings):
                for member in live:
                    member.alone(_stage_alone, member, settings)
        else:
            for member in live:
                member.alone(_stage_alone, member, settings)
        live = [m for m in live if not m.failed]
    for member in live:
        member.run = member.setup.ran(PipelineResult(member.x, member.loss, member.done))


def _stage_alone(member: _Member, settings: Settings) -> None:
    """One stage of one fit, as ``register`` runs it."""
    result = run_stages((settings,), member.posed.space, member.setup.objective, member.x, timer=member.timer,
                        first_iteration=member.done)
    member.x, member.done, member.loss = result.vertices, member.done + result.iterations, result.loss


def _stage_together(members: list[_Member], settings: Settings) -> bool:
    """One gradient stage of every member at once; False (the members unchanged) if it failed."""
    started = time.perf_counter()
    timer = StageTimer()
    try:
        objective = ScanBatch([m.setup.scan for m in members], [m.setup.landmarks for m in members])
        objective.with_landmarks(settings.landmarks)
        param, optimizer = build(settings, members[0].posed.space, torch.stack([m.x for m in members]))
        result = run_fit(param, optimizer, objective, settings.iterations, timer=timer)
        losses = objective.per_fit(result.vertices)
    except Exception:  # noqa: BLE001 - rerun a fit at a time: each fails, or not, alone
        return False
    share = (time.perf_counter() - started) / len(members)
    for member, x, loss in zip(members, result.vertices, losses):
        member.x, member.done, member.loss = x, member.done + result.iterations, loss
        member.seconds += share
        for name, seconds in timer.seconds.items():
            member.timer.seconds[name] += seconds / len(members)
    return True
