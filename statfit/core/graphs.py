"""One fitting iteration captured in a CUDA graph and replayed: one launch instead of hundreds.

A fitting iteration on a GPU launches hundreds of small kernels (a normal-map iteration ~700), each
costing the host ~5–13 µs whatever its size, so the card idles most of the iteration (docs/
benchmarks.md §12). Captured once in a CUDA graph (``torch.cuda.CUDAGraph``: the parameters'
forward map, the objective, the backward pass and the optimiser's step), every later iteration is
one replay. What the capture needs of the parts (and what :func:`capturable` checks):

- static shapes and no host reads in the iteration: the parametrisation and objective say so with
  ``capturable = True`` (the filters: all but a Laplacian solved by a library whose kernels leave
  torch's stream, :mod:`statfit.core.solvers`); the objective's ``prepare`` does nothing, and it
  checks for divergence at records only (``deferred_checks``);
- an objective that sizes buffers on the device tells the loop after each replay whether they
  still fit (``replayed() -> bool``); when not, the loop runs the next iteration eagerly (which
  sizes them afresh) and captures again;
- the optimisers' step counts live on the device (:func:`statfit.core.optim.make_capturable`);
- nothing the parts keep from one iteration to the next holds its autograd graph (detach what is
  kept): a graph alive at the capture reaches the parameters, whose gradient accumulation then stays
  on the warm-up's stream (torch warns; ``tests/test_graphs.py`` searches the live tensors at each
  capture on a CPU).

The replays run the captured kernels in the captured order on the same memory, so a replayed
iteration computes what the eager one does (the optimiser's bias corrections from a device-side
step count: equal to float rounding). ``STATFIT_CUDA_GRAPHS=0`` turns capturing off. Used by the
fitting loop (:mod:`statfit.core.fit`) and the pose search of inverse rendering
(:mod:`statfit.core.pose`). Measured on an H100: a render iteration 14.9 → 6.0 ms (docs/benchmarks.md §12).
"""
from __future__ import annotations

import os
from typing import Callable

import torch

from statfit.core.optim import CAPTURABLE_OPTIMIZERS, Optimizer, make_capturable

WARMUP = 3          # eager iterations on a side stream before a capture (CUDA's lazy set-up; buffer sizes)

Iteration = Callable[[], tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor]]


def graphs_capture(device: torch.device) -> bool:
    """Whether fits on ``device`` are captured where they can be (CUDA, unless ``STATFIT_CUDA_GRAPHS=0``)."""
    return device.type == "cuda" and os.environ.get("STATFIT_CUDA_GRAPHS", "1") != "0"


def capturable(objective, optimizers: list[Optimizer], device: torch.device, parametrization=None) -> bool:
    """Whether a fit against ``objective`` with ``optimizers`` (and ``parametrization``'s map, when
    one is given) on ``device`` can run as a captured graph."""
    return (graphs_capture(device)
            and (parametrization is None or bool(getattr(parametrization, "capturable", False)))
            and bool(getattr(objective, "capturable", False)) and bool(getattr(objective, "deferred_checks", False))
            and getattr(objective, "optimizer", None) is None
            and all(isinstance(each, CAPTURABLE_OPTIMIZERS) for each in optimizers))


class CapturedIteration:
    """Runs ``iterate()`` (one whole iteration: vertices, loss terms, total; backward and step
    included) eagerly for :data:`WARMUP` iterations on a side stream, then captures it and replays
    it: each iteration, :meth:`ready`, then :meth:`replay` or :meth:`eager`. ``objective`` has
    ``replayed()`` (see :func:`capturable`). ``failure`` holds why a capture failed (the fit then
    goes on eagerly); ``captures`` counts the captures."""

    def __init__(self, iterate: Iteration, optimizers: list[Optimizer], objective):
        self._iterate = iterate
        self._optimizers = optimizers
        self._objective = objective
        self._side = torch.cuda.Stream()
        self._graph: torch.cuda.CUDAGraph | None = None
        self._outputs: tuple | None = None
        self._eager = 0
        self.failure: str | None = None
        self.captures = 0

    def ready(self) -> bool:
        """Capture the iteration if it is due (after the warm-up); whether the next iteration is a replay."""
        if self._graph is None and self.failure is None and self._eager >= WARMUP:
            self._capture()
        return self._graph is not None

    def eager(self) -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor]:
        """One iteration run op by op (on a side stream while warming up for a capture)."""
        self._eager += 1
        if self.failure is not None:
            return self._iterate()
        self._side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(self._side):
            outputs = self._iterate()
        torch.cuda.current_stream().wait_stream(self._side)
        return outputs

    def replay(self) -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor]:
        """One iteration, replayed: its outputs (vertices, terms, total) are overwritten by the next.
        When the objective then finds its buffers too small, the next iterations run eagerly (which
        sizes them afresh) and the iteration is captured again."""
        self._graph.replay()
        outputs = self._outputs
        if self._objective.replayed():
            self._graph, self._outputs, self._eager = None, None, 0
        return outputs

    def _capture(self) -> None:
        if not all(make_capturable(each) for each in self._optimizers):
            self.failure = "an optimiser without a capturable step"
            return
        for each in self._optimizers:
            each.zero_grad(set_to_none=True)
        graph = torch.cuda.CUDAGraph()
        try:
            # thread_local: another thread's fit launching kernels meanwhile is neither captured nor refused.
            with torch.cuda.graph(graph, capture_error_mode="thread_local"):
                outputs = self._iterate()
        except Exception as error:  # noqa: BLE001 — a capture that fails leaves the fit eager, never broken
            self.failure = f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}"
            torch.cuda.synchronize()
            return
        self._graph, self._outputs = graph, outputs
        self.captures += 1
