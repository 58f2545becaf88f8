"""UniformAdam against a hand-computed step and against largesteps' AdamUniform."""
from __future__ import annotations

import math

import pytest
import torch

from statfit.core.optim import UniformAdam


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
