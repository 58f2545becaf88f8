"""UniformAdam against a hand-computed step and against largesteps' AdamUniform; Adam against torch's,
to the bit; neither imports torch's compiler."""
from __future__ import annotations

import math

import pytest
import torch

from statfit.core.optim import Adam, UniformAdam, make_capturable


def test_first_two_steps_by_hand():
    p = torch.tensor([1.0, 2.0, -1.0], dtype=torch.float64, requires_grad=True)
    opt = UniformAdam([p], lr=0.1, betas=(0.9, 0.999), eps=0.0)
    g1 = torch.tensor([0.5, -2.0, 1.0], dtype=torch.float64)
    p.grad = g1.clone()
    opt.step()
    # t=1: m̂ = g, v̂ = g², step = lr · g / max|g| = 0.1 · g / 2
    expected = torch.tensor([1.0, 2.0, -1.0], dtype=torch.float64) - 0.1 * g1 / 2.0
    torch.testing.assert_close(p.detach(), expected)
    g2 = torch.tensor([1.0, 1.0, -3.0], dtype=torch.float64)
    p.grad = g2.clone()
    opt.step()
    m = 0.9 * 0.1 * g1 + 0.1 * g2
    v = 0.999 * 0.001 * g1**2 + 0.001 * g2**2
    m_hat, v_hat = m / (1 - 0.9**2), v / (1 - 0.999**2)
    expected = expected - 0.1 * m_hat / math.sqrt(float(v_hat.max()))
    torch.testing.assert_close(p.detach(), expected)


def test_matches_largesteps_adam_uniform():
    largesteps = pytest.importorskip("largesteps.optimize")
    torch.manual_seed(0)
    a = torch.randn(200, 3, dtype=torch.float64, requires_grad=True)
    b = a.detach().clone().requires_grad_(True)
    ours, theirs = UniformAdam([a], lr=0.01), largesteps.AdamUniform([b], lr=0.01)
    for _ in range(50):
        g = torch.randn(200, 3, dtype=torch.float64)
        a.grad, b.grad = g.clone(), g.clone()
        ours.step()
        theirs.step()
    torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("capturable", [False, True])
def test_a_settling_step_falls_linearly_to_zero_over_the_last_share(capturable):
    """With a constant gradient every Adam step is lr · share(t) (m̂ = g, v̂ = g²), so each step's
    length is the schedule itself: held at lr for t ≤ 6 of 11, then (11 − t)/5 of it, 0 at the last."""
    p = torch.zeros(4, dtype=torch.float64, requires_grad=True)
    opt = UniformAdam([p], lr=0.1, eps=0.0, capturable=capturable, steps=11, settle=0.5)
    lengths = []
    for _ in range(11):
        before = p.detach().clone()
        p.grad = torch.full((4,), -2.0, dtype=torch.float64)
        opt.step()
        lengths.append(float((p.detach() - before)[0]))
    expected = [0.1 * min(1.0, (11 - t) / 5) for t in range(1, 12)]
    assert lengths == pytest.approx(expected, rel=1e-12, abs=1e-15)


def test_settle_is_checked_and_only_for_uniform_adam():
    """Out-of-range values, a Gauss–Newton stage and a torch Adam stage are refused in one line each."""
    from statfit.core.methods import build
    from statfit.core.settings import FitSpace, Settings
    from statfit.errors import StatfitError

    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(StatfitError, match="settle"):
            Settings("laplacian", 10, 0.1, settle=bad)
    with pytest.raises(StatfitError, match="settle"):
        Settings("pca", 10, 0.0, optimizer="gauss-newton", settle=0.5)
    space = FitSpace(torch.zeros(3, 3), torch.eye(2, 9), torch.ones(2), None)
    with pytest.raises(StatfitError, match="settle brings UniformAdam"):
        build(Settings("pca", 10, 0.1, settle=0.5), space, torch.zeros(3, 3))
    assert build(Settings("statistical", 10, 0.1, settle=0.5), space, torch.zeros(3, 3))[1].settle == 0.5


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_adam_steps_as_torchs_adam_to_the_bit(dtype):
    """Two parameter groups of their own learning rates, one parameter without a gradient at some
    steps (it keeps its state and step count, as in torch): every value the same bits as
    ``torch.optim.Adam``'s on a CPU, for 60 steps."""
    torch.manual_seed(1)
    ours = [torch.randn(50, 3, dtype=dtype, requires_grad=True), torch.randn(7, dtype=dtype, requires_grad=True)]
    theirs = [t.detach().clone().requires_grad_(True) for t in ours]

    def groups(params):
        return [{"params": [params[0]]}, {"params": params[1], "lr": 0.3}]

    mine, reference = Adam(groups(ours), lr=0.02), torch.optim.Adam(groups(theirs), lr=0.02)
    for step in range(60):
        for a, b in zip(ours, theirs):
            gradient = torch.randn_like(a) * 10.0 ** (step % 5 - 2)
            a.grad, b.grad = gradient.clone(), gradient.clone()
        if step % 7 == 3:
            ours[1].grad = theirs[1].grad = None
        mine.step()
        reference.step()
        for a, b in zip(ours, theirs):
            assert torch.equal(a, b), (step, (a - b).abs().max())
    assert mine.state[ours[1]]["step"] == int(reference.state[theirs[1]]["step"])


def test_adams_capturable_step_is_its_plain_step():
    """Adam with its step count on the device (switched mid-fit, as the loop does before a CUDA
    capture) takes the plain step's steps, to rounding."""
    torch.manual_seed(2)
    a = torch.randn(40, 3, dtype=torch.float64, requires_grad=True)
    b = a.detach().clone().requires_grad_(True)
    plain, switched = Adam([a], lr=0.05), Adam([b], lr=0.05)
    for step in range(30):
        a.grad = torch.randn(40, 3, dtype=torch.float64)
        b.grad = a.grad.clone()
        plain.step()
        switched.step()
        if step == 3:
            assert make_capturable(switched)
    torch.testing.assert_close(b, a, rtol=0, atol=1e-13)


def test_a_fit_never_imports_torchs_compiler():
    """torch's own optimisers import ``torch._dynamo`` when made (1.0–1.4 s a process), and so does
    ``torch.use_deterministic_algorithms`` (seen on an H200: every CUDA fit's first); a register
    fit and a render fit (its alignment steps Adam) in a fresh process import none of it, nor does
    CUDA's same-seed switch (a CPU can run it: it sets flags), which still sets torch's flag."""
    import subprocess
    import sys

    code = """
import sys
import numpy as np
import statfit
from statfit.model.statmodel import default_model_path
from statfit.structures.normal_map import NormalMap
from statfit.renderer.images import render_target
from statfit.synth.sample import camera_for_view
model = statfit.load_model(default_model_path())
rng = np.random.default_rng(0)
statfit.register(model, model.sample(rng)[::3], "default", align="none", iterations=3, threads=1)
camera = camera_for_view(model.template, 20.0, 5.0, 32)
statfit.reconstruct(model, NormalMap(*render_target(model.template, model.faces, camera)), camera, "default",
                    iterations=3, threads=1)
import torch
from statfit.core.device import same_seed_same_bytes
same_seed_same_bytes()
assert torch.are_deterministic_algorithms_enabled() and torch.is_deterministic_algorithms_warn_only_enabled()
print(sorted(name for name in sys.modules if name.startswith("torch._dynamo")))
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "[]", done.stdout[-500:]
