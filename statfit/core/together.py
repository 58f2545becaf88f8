"""Many fits of one model in one program: each fit keeps its own set-up, clock, warnings and
failures; the gradient stages that can be batched (:func:`statfit.core.methods.batchable`) step all
the fits at once, vertices (B, N, 3), against one data term over the B inputs.

A job that fits many inputs (``register_many``, ``reconstruct_many``) makes a :class:`Member` per
input, sets its ``space``, ``objective`` and start ``x`` alone (:meth:`Member.alone`: a failure is
that fit's one line), then calls :func:`run_stages_together` with a maker of the batched term. A
batched stage that fails is rerun a fit at a time, so only the fits that fail alone fail.
"""
from __future__ import annotations

import threading
import time
import warnings
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Sequence, TypeVar

import torch

from statfit.core.fit import StageTimer, run_fit
from statfit.core.methods import batchable, build
from statfit.core.settings import FitSpace, Settings
from statfit.core.stages import Fit, run_stages
from statfit.core.threads import map_in_threads
from statfit.errors import one_line


# The most fits a batch worker steps together by default on a GPU (issue 38's batch of 64).
MOST_TOGETHER = 64


def fits_in_memory(bytes_per_fit: int, device: torch.device) -> int:
    """How many fits of ``bytes_per_fit`` each a quarter of ``device``'s free memory holds (a GPU,
    where an iteration costs its launches whatever the number of fits), at least 1 and at most
    :data:`MOST_TOGETHER`."""
    free, _ = torch.cuda.mem_get_info(device)
    return int(max(1, min(MOST_TOGETHER, free // 4 // bytes_per_fit)))


@dataclass
class FitOutcome:
    """One input's outcome in a fit of many: its ``fit``, or the one-line ``error`` that stopped it;
    the ``warnings`` it raised, in order."""

    fit: Fit | None = None
    error: str | None = None
    warnings: list[str] = field(default_factory=list)


class Member:
    """One input's fit among many: its outcome, timer and clock; its fit space, data term, current
    vertices ``x`` (N, 3), iterations done and last terms, set by the job."""

    def __init__(self, index: int):
        self.index = index
        self.outcome = FitOutcome()
        self.timer = StageTimer()
        self.seconds = 0.0
        self.space: FitSpace | None = None
        self.objective: Any = None
        self.x: torch.Tensor | None = None
        self.done = 0
        self.loss: dict[str, float] = {}

    @property
    def failed(self) -> bool:
        return self.outcome.error is not None

    def alone(self, work: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """``work(*args, **kwargs)`` on this fit's account: its time, its warnings; a failure becomes its error
        (and None is returned)."""
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                return self._accounted(work, args, kwargs)
            finally:
                self.outcome.warnings += [str(w.message) for w in caught]

    def alone_on_a_thread(self, taken: Callable[[], list[str]], work: Callable[..., Any], *args: Any,
                          **kwargs: Any) -> Any:
        """:meth:`alone` for work that runs beside other fits' on threads of its own, inside
        :func:`warnings_by_thread` (whose ``taken`` hands over this thread's warnings): ``work`` must
        raise its warnings on the thread that calls it."""
        try:
            return self._accounted(work, args, kwargs)
        finally:
            self.outcome.warnings += taken()

    def _accounted(self, work: Callable[..., Any], args: tuple, kwargs: dict[str, Any]) -> Any:
        started = time.perf_counter()
        try:
            return work(*args, **kwargs)
        except Exception as error:  # noqa: BLE001 - a bug or an unforeseen input: this fit's, the others go on
            self.outcome.error = one_line(error)
        finally:
            self.seconds += time.perf_counter() - started
        return None


@contextmanager
def warnings_by_thread() -> Iterator[Callable[[], list[str]]]:
    """Within the block every warning is kept for the thread that raised it (``warnings.catch_warnings``
    is one state for the whole process, so fits on threads side by side cannot each hold one). Yields
    ``taken()``: the calling thread's warnings so far, handed over once."""
    kept: dict[int, list[str]] = defaultdict(list)
    lock = threading.Lock()

    def show(message: Warning | str, *_: Any, **__: Any) -> None:
        with lock:
            kept[threading.get_ident()].append(str(message))

    def taken() -> list[str]:
        with lock:
            return kept.pop(threading.get_ident(), [])

    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = show
        yield taken


M = TypeVar("M", bound=Member)


def each_alone(members: Sequence[M], work: Callable[[M], Any], threads: int = 1) -> list[Any]:
    """``member.alone(work, member)`` for every member, in order, up to ``threads`` of them side by side
    on threads (host work one fit leaves cores idle in; their warnings kept per thread,
    :func:`warnings_by_thread`): what one after another gives, where ``work`` shares nothing it
    changes with another member's and raises its warnings on the thread that calls it."""
    if threads <= 1 or len(members) <= 1:
        return [member.alone(work, member) for member in members]
    with warnings_by_thread() as taken:
        return map_in_threads(lambda member: member.alone_on_a_thread(taken, work, member), members, threads)


BatchedTerm = Callable[[Sequence[Member], Settings], Any]


def run_stages_together(members: Sequence[Member], stages: Sequence[Settings], batched_term: BatchedTerm,
                        side_by_side: int = 1) -> None:
    """Run ``stages`` on every member that has not failed, from its ``x``: batchable stages of two
    or more fits together against ``batched_term(members, settings)`` (an objective over (B, N, 3)
    vertices with ``per_fit``), the others a fit at a time, ``side_by_side`` of them at once
    (:func:`each_alone`); a batched stage that fails is rerun a fit at a time. Each member's ``x``,
    ``done`` and ``loss`` move on."""
    live = [m for m in members if not m.failed]
    for settings in stages:
        if not (len(live) > 1 and batchable(settings) and _stage_together(live, settings, batched_term)):
            each_alone(live, lambda member: _stage_alone(member, settings), side_by_side)
        live = [m for m in live if not m.failed]


def _stage_alone(member: Member, settings: Settings) -> None:
    """One stage of one fit, as the job alone runs it."""
    result = run_stages((settings,), member.space, member.objective, member.x, timer=member.timer,
                        first_iteration=member.done)
    member.x, member.done, member.loss = result.vertices, member.done + result.iterations, result.loss


def _stage_together(members: Sequence[Member], settings: Settings, batched_term: BatchedTerm) -> bool:
    """One gradient stage of every member at once; False (the members unchanged) if it failed."""
    started = time.perf_counter()
    timer = StageTimer()
    try:
        objective = batched_term(members, settings)
        param, optimizer = build(settings, members[0].space, torch.stack([m.x for m in members]))
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
