"""Photometric term of splatting: splats bound to the mesh, rendered into the training views and
compared with the photographs.

Per view: ``(1 − λ)·L1 + λ·(1 − SSIM)`` (λ = 0.2, the 3DGS loss; SSIM with an 11-pixel Gaussian
window, σ 1.5), plus ``mask_weight · mean((α − mask)²)`` where the view has a mask. Each iteration
uses ``views_per_step`` views, going through the training views in a shuffled order (a new
shuffle per pass), as 3DGS does. The splats' own parameters (colours, opacities, scales, angles)
are the objective's: it owns their optimiser, which the fitting loop steps with the vertices'.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from statfit.core.optim import Adam
from statfit.structures.camera import Camera
from statfit.renderer import MeshSplats, render_surfels
from statfit.objectives.weights import MASK_WEIGHT, SSIM_WEIGHT

# Adam step sizes of the splats' parameters (on their logits / logs).
SPLAT_LR = {"colour_logit": 0.03, "opacity_logit": 0.03, "log_scale": 0.01, "angle": 0.01}
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5


@dataclass(frozen=True)
class TrainingView:
    """A view as the objective uses it: camera (in the fit frame), image (H, W, 3), mask (H, W)
    float or None, on the fit's device and dtype."""

    camera: Camera
    image: torch.Tensor
    mask: torch.Tensor | None


def ssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean structural similarity of two images (H, W, C) in [0, 1] (Wang et al. 2004: Gaussian
    window 11 px, σ 1.5; C1 = 0.01², C2 = 0.03²; zero padding as 3DGS's)."""
    channels = image.shape[-1]
    taps = torch.arange(SSIM_WINDOW, dtype=image.dtype, device=image.device) - SSIM_WINDOW // 2
    gauss = torch.exp(-taps**2 / (2 * SSIM_SIGMA**2))
    gauss = gauss / gauss.sum()
    window = (gauss[:, None] * gauss[None, :]).expand(channels, 1, SSIM_WINDOW, SSIM_WINDOW)

    def blur(x: torch.Tensor) -> torch.Tensor:
        return F.conv2d(x, window, padding=SSIM_WINDOW // 2, groups=channels)

    x, y = image.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None]
    mu_x, mu_y = blur(x), blur(y)
    var_x, var_y, cov = blur(x * x) - mu_x**2, blur(y * y) - mu_y**2, blur(x * y) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    value = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
    return value.mean()


def psnr(image: torch.Tensor, target: torch.Tensor) -> float:
    """Peak signal-to-noise ratio in dB of two images in [0, 1]."""
    mse = float((image - target).square().mean())
    return float("inf") if mse == 0 else -10.0 * torch.log10(torch.tensor(mse)).item()


class ImageObjective:
    """Splats on the mesh against photographs, ``views_per_step`` views per iteration."""

    def __init__(self, views: list[TrainingView], splats: MeshSplats, *, views_per_step: int = 1,
                 mask_weight: float = MASK_WEIGHT, ssim_weight: float = SSIM_WEIGHT, seed: int = 0):
        self.views = views
        self.splats = splats
        self.views_per_step = min(views_per_step, len(views))
        self.mask_weight = mask_weight
        self.ssim_weight = ssim_weight
        self.optimizer = Adam([{"params": [tensor], "lr": SPLAT_LR[name]}
                               for name, tensor in splats.parameters().items()])
        self._generator = torch.Generator().manual_seed(seed)
        self._queue: list[int] = []
        self._chosen: list[int] = []

    def prepare(self, vertices: torch.Tensor, iteration: int) -> None:
        """Pick this iteration's views: the next ones of a shuffled pass over all views."""
        self._chosen = []
        while len(self._chosen) < self.views_per_step:
            if not self._queue:
                self._queue = torch.randperm(len(self.views), generator=self._generator).tolist()
            self._chosen.append(self._queue.pop())

    def reset(self) -> None:
        """The splats and their optimiser carry over between stages."""

    def __call__(self, vertices: torch.Tensor) -> dict[str, torch.Tensor]:
        if not self._chosen:
            self.prepare(vertices, 0)
        surfels = self.splats.surfels(vertices)
        terms: dict[str, torch.Tensor] = {}
        for index in self._chosen:
            view = self.views[index]
            rendered = render_surfels(surfels, view.camera)
            for name, value in self.view_terms(rendered.colour, rendered.alpha, view).items():
                terms[name] = terms.get(name, 0.0) + value / len(self._chosen)
        return terms

    def view_terms(self, colour: torch.Tensor, alpha: torch.Tensor, view: TrainingView) -> dict[str, torch.Tensor]:
        """The loss terms of one rendered view: colour (H, W, 3), alpha (H, W)."""
        terms = {"l1": (1.0 - self.ssim_weight) * (colour - view.image).abs().mean(),
                 "dssim": self.ssim_weight * (1.0 - ssim(colour, view.image))}
        if self.mask_weight and view.mask is not None:
            terms["mask"] = self.mask_weight * (alpha - view.mask).square().mean()
        return terms
