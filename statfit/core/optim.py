"""UniformAdam (Nicolet et al. 2021): Adam whose step is divided by the square root of the
*largest* bias-corrected second moment instead of each entry's own, so the step direction
is the filtered gradient's direction (per-entry scaling would undo the filter). Its step size may
settle: fall linearly to 0 over the last share of a known number of steps.

:func:`make_capturable` turns an optimiser's step count into a tensor on its parameters' device, so
the step can be captured in a CUDA graph (its bias corrections then change on every replay)."""
from __future__ import annotations

import torch


class UniformAdam(torch.optim.Optimizer):
    """``p -= lr * m̂ / (eps + sqrt(max(v̂)))`` with Adam's moment estimates m̂, v̂.

    ``capturable``: the step count t is a tensor on the parameter's device and the bias corrections
    are computed there (a few more, tiny ops; no value of t is baked into the launched kernels).
    ``fits``: a parameter's first dimension indexes independent fits (B, ...): each takes its own
    largest second moment, so each steps as it would alone. ``settle`` s > 0 with ``steps`` T: the
    step size at step t (1 … T) is lr · min(1, (T − t) / (s (T − 1))), held until the last share s
    of the steps, then falling linearly to 0 at the last."""

    def __init__(self, params, lr: float = 0.01, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8,
                 capturable: bool = False, fits: bool = False, steps: int = 1, settle: float = 0.0):
        super().__init__(params, dict(lr=lr, betas=betas, eps=eps, capturable=capturable, fits=fits))
        self.steps, self.settle = steps, settle

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
                m, v = state["m"], state["v"]
                m.mul_(b1).add_(p.grad, alpha=1 - b1)
                v.mul_(b2).addcmul_(p.grad, p.grad, value=1 - b2)
                largest = v.flatten(1).amax(dim=1).view(-1, *(1,) * (p.dim() - 1)) if group["fits"] else v.max()
                if group["capturable"]:
                    t = _step_tensor(state, p).add_(1)
                    denom = (largest / (1 - b2 ** t)).sqrt_().add_(group["eps"])
                    size = group["lr"] / (1 - b1 ** t)
                    p.sub_(m.mul(size * self._share(t) if self.settle else size).div_(denom))
                    continue
                state["step"] += 1
                t = state["step"]
                denom = (largest / (1 - b2**t)).sqrt_().add_(group["eps"])
                size = group["lr"] / (1 - b1**t)
                p.sub_(m / denom, alpha=size * self._share(t) if self.settle else size)

    def _share(self, t):
        """The settling share of the step size at step ``t`` (a number, or a tensor on the device)."""
        share = (self.steps - t) / (self.settle * max(self.steps - 1, 1))
        return share.clamp(0.0, 1.0) if isinstance(share, torch.Tensor) else min(max(share, 0.0), 1.0)


# The optimisers whose steps :func:`make_capturable` can switch to a device-side step count.
CAPTURABLE_OPTIMIZERS = (UniformAdam, torch.optim.Adam)


def _step_tensor(state: dict, p: torch.Tensor) -> torch.Tensor:
    """The state's step count as a float64 tensor () on ``p``'s device (converted once)."""
    step = state["step"]
    if not isinstance(step, torch.Tensor) or step.device != p.device or step.dtype != torch.float64:
        step = state["step"] = torch.as_tensor(float(step), dtype=torch.float64, device=p.device)
    return step


def make_capturable(optimizer: torch.optim.Optimizer) -> bool:
    """Switch ``optimizer`` (UniformAdam or torch's Adam) to steps that a CUDA graph can capture,
    keeping its state; False (and unchanged) for any other optimiser."""
    if not isinstance(optimizer, CAPTURABLE_OPTIMIZERS):
        return False
    if isinstance(optimizer, torch.optim.Adam):
        if any(group.get(flag) for group in optimizer.param_groups for flag in ("fused", "differentiable")):
            return False
        for group in optimizer.param_groups:
            group["capturable"] = True
            for p in group["params"]:
                state = optimizer.state.get(p)
                if state and "step" in state:
                    state["step"] = state["step"].to(device=p.device, dtype=torch.float32)
        return True
    for group in optimizer.param_groups:
        group["capturable"] = True
        for p in group["params"]:
            if optimizer.state.get(p):
                _step_tensor(optimizer.state[p], p)
    return True
