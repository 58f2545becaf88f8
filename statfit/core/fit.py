"""The one fitting loop shared by every job and method."""
from __future__ import annotations

import functools
import math
import operator
import os
import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Callable, Protocol

import torch

from statfit.core.graphs import CapturedIteration, capturable
from statfit.core.optim import Optimizer
from statfit.errors import DivergenceError


class Objective(Protocol):
    """A data term: ``prepare`` does non-differentiable work (correspondences, visibility), ``reset``
    drops what ``prepare`` keeps (a new stage starts afresh), ``__call__`` returns named loss terms
    (scalars) differentiable w.r.t. ``vertices``. An objective with parameters of its own (the
    splats' colours) has an ``optimizer`` attribute; the loop steps it with the vertices'.

    ``deferred_checks = True`` (optional attribute) says the objective survives non-finite vertices
    until the next record step (its ``prepare`` raises DivergenceError where it cannot): the loop
    then checks for divergence at record steps only, with the loss values in one host read, and no
    other iteration waits for the device. Without it the vertices are checked every iteration.

    ``capturable = True`` (optional) says a CUDA graph can capture a whole iteration with it
    (:mod:`statfit.core.graphs`: static shapes, no host reads, ``prepare`` does nothing, checks
    deferred); such an objective has ``replayed() -> bool``, called after each replay, True when
    the captured iteration no longer fits its buffers."""

    def prepare(self, vertices: torch.Tensor, iteration: int) -> None: ...

    def reset(self) -> None: ...

    def __call__(self, vertices: torch.Tensor) -> dict[str, torch.Tensor]: ...


class Parametrization(Protocol):
    """Parameters and a differentiable map from them to the vertices (:mod:`statfit.core.parametrize`)."""

    def parameters(self) -> list[torch.Tensor]: ...

    def vertices(self) -> torch.Tensor: ...

    def prior(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """The parametrisation's own loss terms at ``x`` (for the record; their gradient is in x's)."""


@dataclass
class StageTimer:
    """Accumulates wall time per named stage. On a GPU a stage's time is the host's (the kernels it
    launched may still run); ``sync`` waits for the device at the end of every stage so the times
    are the device's, at the price of five host waits an iteration (the device idles while the host
    launches the next stage's kernels): :meth:`for_device` turns it on only where
    ``STATFIT_SYNC_TIMES=1`` asks."""

    sync: bool = False
    seconds: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    notes: dict[str, str] = field(default_factory=dict)     # e.g. "graph": whether the loop was captured

    @classmethod
    def for_device(cls, device: torch.device) -> StageTimer:
        """A timer for a fit on ``device``: synchronising only on CUDA and where ``STATFIT_SYNC_TIMES=1``."""
        return cls(sync=device.type == "cuda" and os.environ.get("STATFIT_SYNC_TIMES") == "1")

    def __call__(self, name: str):
        return _Timed(self, name)


class _Timed:
    def __init__(self, timer: StageTimer, name: str):
        self.timer, self.name = timer, name

    def __enter__(self):
        self.start = time.perf_counter()

    def __exit__(self, *exc):
        if self.timer.sync and torch.cuda.is_available():
            torch.cuda.synchronize()
        self.timer.seconds[self.name] += time.perf_counter() - self.start


@dataclass
class FitResult:
    vertices: torch.Tensor
    loss: dict[str, float]
    iterations: int
    seconds: float


Progress = Callable[[int, dict[str, float]], None]
Snapshot = Callable[[int, torch.Tensor], None]


def run_fit(param: Parametrization, optimizer: Optimizer, objective: Objective, iterations: int,
            *, on_record: Progress | None = None, record_every: int = 10, timer: StageTimer | None = None,
            first_iteration: int = 0, on_snapshot: Snapshot | None = None) -> FitResult:
    """Minimise ``objective`` over ``param`` for ``iterations`` steps.

    ``on_record(iteration, terms)`` is called every ``record_every`` iterations and at the end;
    ``on_snapshot(iteration, vertices)``, at the same iterations, gets the vertices the loss was
    evaluated at (detached; e.g. to trace the error against a ground truth).
    Raises DivergenceError naming the iteration when the loss stops being finite.
    """
    timer = timer or StageTimer()
    # Filtered gradients decay to subnormal floats far from the data; on CPUs those are ~100x slower.
    flushed = torch.set_flush_denormal(True)
    try:
        return _loop(param, optimizer, objective, iterations, on_record, record_every, timer, first_iteration,
                     on_snapshot)
    finally:
        if flushed:
            torch.set_flush_denormal(False)


def _loop(param: Parametrization, optimizer: Optimizer, objective: Objective, iterations: int,
          on_record: Progress | None, record_every: int, timer: StageTimer, first_iteration: int,
          on_snapshot: Snapshot | None) -> FitResult:
    start = time.perf_counter()
    terms: dict[str, float] = {}
    optimizers = [optimizer, *filter(None, [getattr(objective, "optimizer", None)])]
    # An objective that survives non-finite vertices between records (ScanObjective) lets the loop
    # check for divergence at its record steps only: no host wait in the other iterations.
    deferred = bool(getattr(objective, "deferred_checks", False))
    pending: list[torch.Tensor] = []    # the total loss of every iteration since the last record
    it = first_iteration

    def iterate() -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor]:
        with timer("filter"):
            x = param.vertices()
        if not deferred and not bool(torch.isfinite(x.detach()).all()):
            raise DivergenceError(f"the fit diverged at iteration {it}: vertices are not finite (step size too large?)")
        with timer("correspondences"):
            try:
                objective.prepare(x.detach(), it)
            except DivergenceError:
                _check_pending(pending, it - len(pending))
                raise DivergenceError(f"the fit diverged at iteration {it}: vertices are not finite "
                                      "(step size too large?)") from None
        with timer("loss"):
            losses = objective(x) | param.prior(x)
            loss = functools.reduce(operator.add, losses.values())
        with timer("backward"):
            for each in optimizers:
                _clear_grads(each)
            loss.backward()
        with timer("step"):
            for each in optimizers:
                each.step()
        return x, losses, loss

    parameters = param.parameters()
    captured = CapturedIteration(iterate, optimizers, objective) \
        if parameters and capturable(objective, optimizers, parameters[0].device, param) else None
    for step in range(iterations):
        it = first_iteration + step
        replayed = captured is not None and captured.ready()
        if captured is None:
            x, losses, loss = iterate()
        elif not replayed:
            x, losses, loss = _detached(*captured.eager())
        else:
            with timer("graph"):
                x, losses, loss = _detached(*captured.replay())
                loss = loss.clone()     # the next replay overwrites the total; the record reads it later
        pending.append(loss)
        if step % record_every == 0 or step == iterations - 1:
            terms = _record_terms(losses, pending, x, it, deferred)
            pending = []
            if on_record:
                on_record(it, terms)
            if on_snapshot:
                on_snapshot(it, x.clone() if replayed else x.detach())   # a replay's x is overwritten
    if captured is not None:
        timer.notes["graph"] = captured.failure or f"captured {captured.captures}×"
    with torch.no_grad():
        final = param.vertices().detach()
    if not bool(torch.isfinite(final).all()):
        raise DivergenceError(f"the fit diverged at iteration {first_iteration + iterations - 1}: "
                              "vertices are not finite (step size too large?)")
    return FitResult(final, terms, iterations, time.perf_counter() - start)


def _detached(x: torch.Tensor, losses: dict[str, torch.Tensor], loss: torch.Tensor
              ) -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor]:
    """An iteration's outputs without their autograd graph: held until the next record, a graph kept
    alive across a CUDA graph's capture would tie the parameters' gradient to another stream."""
    return x.detach(), {name: value.detach() for name, value in losses.items()}, loss.detach()


def host_values(values: torch.Tensor) -> list:
    """``values`` on the host as a list: the one read (a wait for the device) of a record step."""
    return values.tolist()


def _clear_grads(optimizer: Optimizer) -> None:
    """``optimizer.zero_grad(set_to_none=True)``, without the profiler's record ops of torch's base method."""
    if type(optimizer).zero_grad is not torch.optim.Optimizer.zero_grad:
        optimizer.zero_grad(set_to_none=True)
        return
    for group in optimizer.param_groups:
        for p in group["params"]:
            p.grad = None


def _record_terms(losses: dict[str, torch.Tensor], pending: list[torch.Tensor], x: torch.Tensor, it: int,
                  deferred: bool) -> dict[str, float]:
    """The loss terms of iteration ``it`` as floats, read with the totals of the iterations since
    the last record (and, for a deferred check, whether ``x`` is finite) in one host read; raises
    DivergenceError naming the first iteration whose loss (or vertices) stopped being finite."""
    with torch.no_grad():
        parts = [torch.stack([v.reshape(()) for v in losses.values()] + pending)]
        if deferred:
            parts.append(torch.isfinite(x).all().reshape(1))
        values = host_values(torch.cat(parts) if deferred else parts[0])
    terms = dict(zip(losses, values))
    totals = values[len(losses):len(losses) + len(pending)]
    if deferred and not values[-1]:
        first = next((i for i, total in enumerate(totals) if not math.isfinite(total)), len(totals) - 1)
        raise DivergenceError(f"the fit diverged at iteration {it - len(totals) + 1 + first}: vertices are not finite "
                              "(step size too large?)")
    for i, total in enumerate(totals):
        if not math.isfinite(total):
            raise DivergenceError(f"the fit diverged at iteration {it - len(totals) + 1 + i}: the loss is {total}")
    terms["total"] = sum(terms.values())
    if not math.isfinite(terms["total"]):
        raise DivergenceError(f"the fit diverged at iteration {it}: the loss is {terms['total']}")
    return terms


def _check_pending(pending: list[torch.Tensor], first: int) -> None:
    """Raise DivergenceError naming the first of the ``pending`` losses (of iterations ``first``, …)
    that is not finite, if one is."""
    if pending:
        with torch.no_grad():
            totals = host_values(torch.stack(pending).detach())
        for i, total in enumerate(totals):
            if not math.isfinite(total):
                raise DivergenceError(f"the fit diverged at iteration {first + i}: the loss is {total}")
