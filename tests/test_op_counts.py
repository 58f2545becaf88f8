"""Torch ops and host waits per fitting iteration of ``register`` (issue 38), counted on the CPU.

On a GPU every torch op is a kernel launch and some make the host wait for the device (a read of a
value: ``.item()``, ``float(t)``, boolean-mask compaction, ``nonzero``, ...). A dispatch mode sees
both on a CPU. As ``../shared/tools/sync_count.py`` counts them: paper ``statistical`` on the
embedded model, ``align="none"``, the difference between two fits of different lengths per
iteration, so set-up is not counted. The record step's one read of the loss values
(:func:`statfit.core.fit.host_values`, a ``.tolist()`` that a dispatch mode does not see on a CPU)
is counted as a wait too.

Measured 2026-11-26 (torch 2.13, CPU): 54.8 ops and 0.1 waits per iteration (the record steps'
reads, one per 10 iterations); before the issue: 88 ops and 1.2 waits (a finiteness check of the
vertices every iteration, an ``.any()`` at every refresh, one ``float`` per loss term per record).
53.4 on 2026-11-28, two fewer than the day before (sync_count.py: 55 → 53): UniformAdam no longer
derives from ``torch.optim.Optimizer``, whose step wrapper records a profiler range every step.
"""
from __future__ import annotations

import collections

import numpy as np
import pytest
from torch.utils._python_dispatch import TorchDispatchMode

import statfit.core.fit as fit_loop
from statfit.registration.job import register
from statfit.synth.sample import sample_target, scan_from_view

WAITING = ("_local_scalar_dense", "nonzero", "masked_select", "_unique", "unique_consecutive", "unique_dim",
           "repeat_interleave", "equal", "is_nonzero", "masked_scatter")
SHORT, LONG = 20, 80


class Counter(TorchDispatchMode):
    def __init__(self):
        super().__init__()
        self.ops = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops[func.__name__] += 1
        return func(*args, **(kwargs or {}))


@pytest.fixture(scope="module")
def scan(embedded_model):
    rng = np.random.default_rng(3)
    return scan_from_view(sample_target(embedded_model, rng), embedded_model.faces, rng, 4300, 30.0)


def counted(model, points, iterations: int, monkeypatch) -> tuple[int, int]:
    """(ops, waits) of one paper-statistical fit of ``iterations`` steps."""
    reads = []
    original = fit_loop.host_values
    monkeypatch.setattr(fit_loop, "host_values", lambda values: reads.append(1) or original(values))
    counter = Counter()
    with counter:
        done = register(model, points, "statistical", preset="paper", align="none", iterations=iterations).iterations
    assert done == iterations
    waits = sum(n for name, n in counter.ops.items() if any(w in name for w in WAITING)) + len(reads)
    return sum(counter.ops.values()), waits


def test_register_iteration_ops_and_waits(embedded_model, scan, monkeypatch):
    short_ops, short_waits = counted(embedded_model, scan, SHORT, monkeypatch)
    long_ops, long_waits = counted(embedded_model, scan, LONG, monkeypatch)
    ops = (long_ops - short_ops) / (LONG - SHORT)
    waits = (long_waits - short_waits) / (LONG - SHORT)
    assert ops <= 60, f"{ops:.1f} torch ops per register iteration (issue 38: at most 60)"
    assert waits <= 0.1, f"{waits:.2f} host waits per register iteration (issue 38: at most 0.1)"
