"""UniformAdam (Nicolet et al. 2021): Adam whose step is divided by the square root of the
*largest* bias-corrected second moment instead of each entry's own, so the step direction
is the filtered gradient's direction (per-entry scaling would undo the filter)."""
from __future__ import annotations

import torch


class UniformAdam(torch.optim.Optimizer):
    """``p -= lr * m̂ / (eps + sqrt(max(v̂)))`` with Adam's moment estimates m̂, v̂."""

    def __init__(self, params, lr: float = 0.01, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        super().__init__(params, dict(lr=lr, betas=betas, eps=eps))

    @torch.no_grad()
    def step(self, closure=None):
        for group in self.param_groups:
            b1, b2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                state = self.state[p]
                if not state:
                    state["step"] = 0
                    state["m"] = torch.zeros_like(p)
                    state["v"] = torch.zeros_like(p)
                state["step"] += 1
                m, v, t = state["m"], state["v"], state["step"]
                m.mul_(b1).add_(p.grad, alpha=1 - b1)
                v.mul_(b2).addcmul_(p.grad, p.grad, value=1 - b2)
                denom = (v.max() / (1 - b2**t)).sqrt_().add_(group["eps"])
                p.sub_(m / denom, alpha=group["lr"] / (1 - b1**t))
