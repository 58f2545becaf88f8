"""Torch ops and host waits per iteration of `render` (issue 38), counted on the CPU with a dispatch
mode as ../shared/tools/sync_count.py counts them: on a GPU every op is a kernel launch and every
wait (a device-to-host read) a stall, so both are held down here.

The iteration's difference between two fits of different lengths is what is counted, so the set-up
(buffers sized at the first call, with host reads) is not."""
from __future__ import annotations

import collections
import traceback

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from statfit.objectives.normals import NormalMapObjective
from statfit.render.job import camera_space_normals, reconstruct

from conftest import normal_map_scene

WAITING = ("_local_scalar_dense", "nonzero", "masked_select", "_unique", "unique_consecutive", "unique_dim",
           "repeat_interleave", "equal", "is_nonzero", "masked_scatter")
SIZE = 64


class Counter(TorchDispatchMode):
    """Ops by name; waits by name and by whether a frame of the renderer or the objective asked."""

    def __init__(self):
        super().__init__()
        self.ops = collections.Counter()
        self.render_waits = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.__name__
        self.ops[name] += 1
        if any(w in name for w in WAITING):
            files = [frame.filename for frame in traceback.extract_stack()]
            self.render_waits += any("renderer" in f or "objectives" in f for f in files)
        return func(*args, **(kwargs or {}))

    def waits(self) -> int:
        return sum(v for k, v in self.ops.items() if any(w in k for w in WAITING))


def _per_iteration(run, short: int, long: int) -> tuple[float, float, float]:
    counters = []
    for iterations in (short, long):
        counter = Counter()
        with counter:
            run(iterations)
        counters.append(counter)
    n = long - short
    first, second = counters
    return ((sum(second.ops.values()) - sum(first.ops.values())) / n, (second.waits() - first.waits()) / n,
            (second.render_waits - first.render_waits) / n)


def test_the_objective_runs_without_host_waits_in_few_ops(embedded_model):
    """One objective evaluation and its backward (64² map): measured 2026-11-26 at 743 ops (the
    general rasteriser's path: ~990, 13 host waits) and 1/16 host reads (the renderer's overflow
    check, every 16th call). 694 before the per-pixel normals were set up per triangle: 49 ops
    more (triangle-sized) for 13–17% less time a call at 512² on one CPU thread. 752 since 2026-11-27:
    products over a size-3 axis added in order (the same bits) instead of made whole and summed, for
    3–9% less time a call (ICT, 128² and 512², one thread; docs/benchmarks.md §12). 754 since
    2026-11-27 (session 23): masked lanes write zeros to distinct slots instead of one dump slot,
    which CUDA's deterministic scatters serialise (docs/method.md)."""
    normal_map, camera = normal_map_scene(embedded_model, SIZE)
    target = camera_space_normals(normal_map, camera)
    faces = torch.as_tensor(embedded_model.faces, dtype=torch.long)
    start = torch.as_tensor(embedded_model.template, dtype=torch.float32)

    def run(calls: int) -> None:
        objective = NormalMapObjective(torch.as_tensor(target, dtype=torch.float32),
                                       torch.as_tensor(normal_map.mask), camera, faces)
        for _ in range(calls):
            x = start.clone().requires_grad_()
            sum(objective(x).values()).backward()

    ops, waits, _ = _per_iteration(run, 16, 48)
    assert waits <= 0.1, waits
    assert ops <= 760, ops


@pytest.mark.parametrize("gpu_path, most", [(False, 785), (True, 760)], ids=["cpu-path", "gpu-path"])
def test_a_render_iteration_counts(embedded_model, monkeypatch, gpu_path, most):
    """`reconstruct` (paper statistical, --align none): ops per iteration, and no host wait asked by
    the renderer or the objective beyond the overflow check. Measured 2026-11-26 (64² here; 729 at
    256² as sync_count.py counts, from 1,030): 768 ops per iteration in all (729 before the
    per-triangle set-up of the pixel normals) — the issue's target of
    150 is NOT reached (the loop's own ~40, ~620 forward and ~70 backward ops of the render) — and
    0.06 waits per iteration in all (the renderer's overflow check every 16th call; 1.3 before the
    normal-map objective deferred the loop's finiteness test to its record steps). 775 since
    2026-11-27: products over a size-3 axis added in order (the same bits) instead of made whole and
    summed, for 3–9% less time an iteration on one CPU thread (docs/benchmarks.md §12). 777 since
    session 23: no dump slot for CUDA's deterministic scatters to serialise (docs/method.md). 775
    since 2026-11-28: the optimisers' steps record no profiler range (statfit.core.optim). 776 since
    session 33: the renderer's kept screen positions detached (no autograd graph kept across a CUDA
    capture, tests/test_graphs.py).

    The renderer's GPU path (``lookups``: slots looked up, masked writes spread) is counted on a CPU
    too: a host wait there would end every CUDA capture, and no CPU run would see it. 749 ops per
    iteration in session 23."""
    if gpu_path:
        from statfit.renderer import steady_buffers

        made = steady_buffers.SteadyBuffers.__init__

        def on_a_gpu(self, device):
            made(self, device)
            self.lookups = True

        monkeypatch.setattr(steady_buffers.SteadyBuffers, "__init__", on_a_gpu)
    normal_map, camera = normal_map_scene(embedded_model, SIZE)

    def run(iterations: int) -> int:
        return reconstruct(embedded_model, normal_map, camera, "statistical", preset="paper", align="none",
                           iterations=iterations, threads=1).iterations

    ops, waits, render_waits = _per_iteration(run, 20, 52)
    assert render_waits <= 0.1, (render_waits, waits)
    assert waits <= 0.1, waits
    assert ops <= most, ops


def test_a_default_render_iteration_reusing_the_visibility_counts_fewer_ops(embedded_model):
    """A tuned stage's iteration (`statistical`, --align none), the visibility reused for
    ``VISIBILITY_EVERY`` = 4 calls as shipped (docs/studies.md §31): 454 ops per iteration on average
    at 64², measured 2026-11-27 (777 refreshing every call; 452 and 775 since 2026-11-28), and no host wait."""
    from statfit.render.visibility import VISIBILITY_EVERY

    assert VISIBILITY_EVERY == 4
    normal_map, camera = normal_map_scene(embedded_model, SIZE)

    def run(iterations: int) -> int:
        return reconstruct(embedded_model, normal_map, camera, "statistical", align="none", iterations=iterations,
                           threads=1, device="cpu").iterations     # a captured CUDA fit refreshes every call

    ops, waits, _ = _per_iteration(run, 20, 84)
    assert waits <= 0.1, waits
    assert ops <= 470, ops
