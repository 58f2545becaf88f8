"""The fits' optimisers: UniformAdam (Nicolet et al. 2021), Adam whose step is divided by the square
root of the *largest* bias-corrected second moment instead of each entry's own, so the step direction
is the filtered gradient's direction (per-entry scaling would undo the filter), its step size
settling linearly to 0 over the last share of a known number of steps if asked; and Adam, step for
step torch's (``torch.optim.Adam``'s arithmetic on a CPU, to the bit), for the baselines, the render
alignment and the splats.

Neither derives from ``torch.optim.Optimizer``: constructing one of those imports ``torch._dynamo``
(its ``add_param_group`` is wrapped to disable the compiler), 1.0–1.4 s of every process's first
fit that statfit never uses (docs/benchmarks.md §17). A fit needs only parameter groups, per-parameter
state, ``step`` and ``zero_grad``; a plugin's method may still return any torch optimiser.

:func:`make_capturable` turns an optimiser's step count into a tensor on its parameters' device, so
the step can be captured in a CUDA graph (its bias corrections then change on every replay)."""
from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Iterator
from typing import Any

import torch


class ParameterGroups:
    """What a fit uses of an optimiser: ``param_groups`` (dicts: ``params``, a list of tensors, and
    the settings, a group's own overriding ``defaults``), ``state`` (a dict per parameter) and
    :meth:`zero_grad`. ``params``: tensors, or dicts of ``params`` and settings, one per group."""

    def __init__(self, params: Iterable[torch.Tensor] | Iterable[dict[str, Any]], defaults: dict[str, Any]):
        groups = list(params)
        if not groups:
            raise ValueError("optimizer got an empty parameter list")
        if not isinstance(groups[0], dict):
            groups = [{"params": groups}]
        self.defaults = defaults
        self.param_groups = [{**defaults, **group, "params": _tensors(group["params"])} for group in groups]
        self.state: defaultdict[torch.Tensor, dict[str, Any]] = defaultdict(dict)

    def _stepped(self) -> Iterator[tuple[dict[str, Any], torch.Tensor, dict[str, Any]]]:
        """(group, parameter, its state) for every parameter with a gradient, the state made at the
        first: a step count of 0 and Adam's two moments ``m``, ``v`` at zero."""
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is None:
                    continue
                state = self.state[p]
                if not state:
                    state.update(step=0, m=torch.zeros_like(p), v=torch.zeros_like(p))
                yield group, p, state

    def zero_grad(self, set_to_none: bool = True) -> None:
        """Forget every parameter's gradient (``set_to_none=False``: zero it in place)."""
        for group in self.param_groups:
            for p in group["params"]:
                if set_to_none:
                    p.grad = None
                elif p.grad is not None:
                    p.grad.detach_().zero_()


def _tensors(params: torch.Tensor | Iterable[torch.Tensor]) -> list[torch.Tensor]:
    return [params] if isinstance(params, torch.Tensor) else list(params)


Optimizer = ParameterGroups | torch.optim.Optimizer     # what a method's builder may return


class UniformAdam(ParameterGroups):
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
        for group, p, state in self._stepped():
            b1, b2 = group["betas"]
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


class Adam(ParameterGroups):
    """Adam (Kingma and Ba 2015) as torch 2.13's ``torch.optim.Adam`` steps one tensor at a time
    (its arithmetic on a CPU, to the bit: tests/test_optim.py), without weight decay, AMSGrad or
    maximising. ``capturable``: the step count is a float64 tensor on the parameter's device and the
    bias corrections are computed there, in the order torch's capturable step takes."""

    def __init__(self, params, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8,
                 capturable: bool = False):
        super().__init__(params, dict(lr=lr, betas=betas, eps=eps, capturable=capturable))

    @torch.no_grad()
    def step(self, closure=None):
        for group, p, state in self._stepped():
            (b1, b2), lr, eps = group["betas"], group["lr"], group["eps"]
            m, v = state["m"], state["v"]
            m.lerp_(p.grad, 1 - b1)
            v.mul_(b2).addcmul_(p.grad, p.grad, value=1 - b2)
            if group["capturable"]:
                t = _step_tensor(state, p).add_(1)
                step_size_neg = (lr / (1 - b1**t)).neg()
                denom = (v.sqrt() / ((1 - b2**t).sqrt() * step_size_neg)).add_(eps / step_size_neg)
                p.addcdiv_(m, denom)
                continue
            state["step"] += 1
            t = float(state["step"])
            denom = (v.sqrt() / (1 - b2**t) ** 0.5).add_(eps)
            p.addcdiv_(m, denom, value=-(lr / (1 - b1**t)))


# The optimisers whose steps :func:`make_capturable` can switch to a device-side step count.
CAPTURABLE_OPTIMIZERS = (UniformAdam, Adam)


def _step_tensor(state: dict, p: torch.Tensor) -> torch.Tensor:
    """The state's step count as a float64 tensor () on ``p``'s device (converted once)."""
    step = state["step"]
    if not isinstance(step, torch.Tensor) or step.device != p.device or step.dtype != torch.float64:
        step = state["step"] = torch.as_tensor(float(step), dtype=torch.float64, device=p.device)
    return step


def make_capturable(optimizer: Optimizer) -> bool:
    """Switch ``optimizer`` (UniformAdam or Adam) to steps that a CUDA graph can capture, keeping its
    state; False (and unchanged) for any other optimiser (a plugin's torch optimiser steps uncaptured)."""
    if not isinstance(optimizer, CAPTURABLE_OPTIMIZERS):
        return False
    for group in optimizer.param_groups:
        group["capturable"] = True
        for p in group["params"]:
            if optimizer.state.get(p):
                _step_tensor(optimizer.state[p], p)
    return True
