"""Gradient-based rigid or similarity pose of a fixed shape against any differentiable objective."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from statfit.core.graphs import CapturedIteration, capturable
from statfit.core.optim import Adam
from statfit.geometry.align import Similarity
from statfit.structures.camera import Camera
from statfit.structures.frame import Frame

Loss = Callable[[torch.Tensor], dict[str, torch.Tensor]]


@dataclass(frozen=True)
class PoseFit:
    """The best pose found, its (unposed) shape (N, 3) and the objective's value there."""

    pose: Similarity
    shape: torch.Tensor
    loss: float


# Weight of the Gaussian prior on the shape coefficients fitted with the pose: weak, so the pose
# does not absorb differences of shape (docs/method.md, the inverse-rendering alignment).
SHAPE_PRIOR = 1e-3
SETTLE_WINDOW = 25   # iterations between the early stop's reads of the best value


def _skew(omega: torch.Tensor) -> torch.Tensor:
    zero = omega.new_zeros(())
    x, y, z = omega.unbind()
    return torch.stack([torch.stack([zero, -z, y]), torch.stack([z, zero, -x]), torch.stack([-y, x, zero])])


def rotation_of(omega: torch.Tensor) -> torch.Tensor:
    """exp([ω]×) (3, 3) for a rotation vector ω (3,), by Rodrigues' formula
    I + (sin θ/θ) K + ((1 − cos θ)/θ²) K², K = [ω]×, θ = |ω| (the series below 1e-4 rad, with finite
    gradients at ω = 0). ``torch.linalg.matrix_exp`` gives the same matrix, but on CUDA it reads the
    norm back to the host (forward and backward): no CUDA graph could capture it."""
    skew = _skew(omega)
    squared = omega.square().sum()
    small = squared < 1e-8
    theta = torch.where(small, 1.0, squared).sqrt()
    first = torch.where(small, 1.0 - squared / 6.0, theta.sin() / theta)
    second = torch.where(small, 0.5 - squared / 24.0, (1.0 - theta.cos()) / torch.where(small, 1.0, squared))
    return torch.eye(3, dtype=omega.dtype, device=omega.device) + first * skew + second * (skew @ skew)


def fit_pose(vertices: torch.Tensor, loss: Loss, *, with_scale: bool = False, iterations: int = 200,
             lr: float = 0.01, start: Similarity | None = None, fixed_axis: torch.Tensor | None = None,
             shape_basis: torch.Tensor | None = None, shape_prior: float = SHAPE_PRIOR, shape_lr: float | None = None,
             move: bool = True, settle: float | None = None, centre: torch.Tensor | None = None) -> PoseFit:
    """The pose y = s·R·x + t of ``vertices`` (N, 3) that minimises ``sum(loss(y).values())``.

    Adam on a rotation vector (exponential map), a translation and, ``with_scale``, log s; the
    rotation and scale act about ``centre`` (3,) (default: the vertices' centroid). ``lr`` is in the vertices' units (and
    radians). ``fixed_axis`` (3,) unit: the translation keeps its component along it (e.g. a
    camera's viewing axis, along which one view barely constrains it). Starts from ``start``
    (default: the identity). ``shape_basis`` (K, N, 3): the shape varies jointly as
    ``vertices + Σ c_k basis_k`` with a penalty ``shape_prior·‖c‖²``, so that the pose need not
    explain differences of shape, each coefficient at Adam's step ``shape_lr`` (default ``lr``);
    ``move=False`` keeps the pose at ``start`` and fits the shape only. ``settle``: stop early once
    the best value has fallen by less than this share of itself over the last ``SETTLE_WINDOW``
    iterations (one host read per window). Returns the best pose seen, with its shape and
    objective value.
    """
    dtype, device = vertices.dtype, vertices.device
    centre = vertices.detach().mean(dim=0) if centre is None else centre
    start = start or Similarity()
    base = torch.as_tensor(start.rotation, dtype=dtype, device=device)
    identity = torch.eye(3, dtype=dtype, device=device)
    shift = torch.as_tensor(start.translation, dtype=dtype, device=device) + (start.scale * base - identity) @ centre
    omega = torch.zeros(3, dtype=dtype, device=device, requires_grad=True)
    free = identity
    if fixed_axis is not None:
        axis = fixed_axis.to(dtype=dtype, device=device)
        free = free - torch.outer(axis, axis)
    step = torch.zeros(3, dtype=dtype, device=device, requires_grad=True)
    log_scale = torch.tensor(float(np.log(start.scale)), dtype=dtype, device=device, requires_grad=with_scale)
    coefficients = torch.zeros(0 if shape_basis is None else len(shape_basis), dtype=dtype, device=device,
                               requires_grad=shape_basis is not None)
    groups = [{"params": [omega, step] + ([log_scale] if with_scale else [])}] if move else []
    if shape_basis is not None:
        groups.append({"params": [coefficients], "lr": lr if shape_lr is None else shape_lr})
    optimizer = Adam(groups, lr=lr)
    centred = vertices.detach() - centre

    def shape() -> torch.Tensor:
        if shape_basis is None:
            return centred
        return centred + torch.tensordot(coefficients, shape_basis, dims=1)

    def posed() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        rotation = rotation_of(omega) @ base
        translation = shift + free @ step
        return log_scale.exp() * shape() @ rotation.T + centre + translation, rotation, translation

    # The best pose seen, kept on the device (no host read an iteration): value, scale, R, t, shape.
    best = [torch.full((), torch.inf, dtype=dtype, device=device), log_scale.detach().exp(), base.clone(),
            shift.clone(), vertices.detach().clone()]

    def iterate() -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor]:
        optimizer.zero_grad(set_to_none=True)
        y, rotation, translation = posed()
        value = sum(loss(y).values()) + shape_prior * coefficients.square().sum()
        with torch.no_grad():
            better = value < best[0]
            seen = (value, log_scale.exp(), rotation, translation, shape() + centre)
            for kept, now in zip(best, seen):
                kept.copy_(torch.where(better, now, kept))
        value.backward()
        optimizer.step()
        return y, {"value": value}, value

    captured = CapturedIteration(iterate, [optimizer], loss) if capturable(loss, [optimizer], device) else None
    before = float("inf")
    for done in range(1, iterations + 1):
        if captured is None:
            iterate()
        elif captured.ready():
            captured.replay()
        else:
            captured.eager()
        if settle is not None and done % SETTLE_WINDOW == 0:
            now = float(best[0])
            if before - now <= settle * abs(now):
                break
            before = now
    best_value, scale, rotation, translation, best_shape = best
    rotation = rotation.double().cpu().numpy()
    centre64 = centre.double().cpu().numpy()
    # y = s R (x − c) + c + t  ⇒  t' = c + t − s R c
    scale = float(scale)
    pose = Similarity(scale, rotation, centre64 + translation.double().cpu().numpy() - scale * rotation @ centre64)
    return PoseFit(pose, best_shape, float(best_value))


def camera_in_frame(camera: Camera, frame: Frame, pose: Similarity = Similarity()) -> Camera:
    """The camera that sees unit-frame points x as ``camera`` sees world points
    ``frame.from_unit(pose.apply(x))`` (same image; camera coordinates divided by the scales)."""
    R, t = camera.rotation.numpy(), camera.world_to_camera[:3, 3].numpy()
    scale = frame.scale * pose.scale
    matrix = np.eye(4)
    matrix[:3, :3] = R @ pose.rotation
    matrix[:3, 3] = (R @ (frame.scale * pose.translation + frame.center) + t) / scale
    return Camera(camera.width, camera.height, camera.K, matrix)
