"""Texture inpainting: fit all pixels of an image to its visible pixels (L1) through a gradient
filter, so the holes are filled by what the filter spreads into them (docs/method.md, "Texture
inpainting").

The image is the "vertex" array x (H·W, C); ``FilteredVertices``/``PCACoefficients``, the filters,
UniformAdam and ``run_fit`` are the mesh fit's own. The hybrid filter's Laplacian is the pixel grid's
(:mod:`statfit.texture.grid`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from statfit.core.device import resolve_device
from statfit.errors import DivergenceError, StatfitError
from statfit.core.fit import Progress
from statfit.core.methods import METHODS, resolve
from statfit.core.settings import FitSpace, Settings
from statfit.core.stages import run_stages
from statfit.texture.grid import grid_laplacian
from statfit.texture.model import TextureModel
from statfit.texture.resample import resize_image, resize_labels, resize_mask

STARTS = ("mean", "reconstruction")
# Pixel noise (standard deviation, in [0, 1] colour units) assumed by the model-only reconstruction.
PROJECTION_NOISE = 0.02
# A fill whose hole colours lie, at the median, this far outside the range of the image's seen colours
# (in units of that range, at least 1: [0, 1] for an 8-bit image) ran away: `--lr 1e9` filled a hole
# with ±1e6; a converged fill overshoots the range by a few hundredths of it.
RUNAWAY_COLOUR = 1.0


@dataclass
class Inpainting:
    """result (H, W, C): the input on visible pixels, the fit in the holes; model_only (H, W, C):
    the model's reconstruction from the visible pixels (None without a model); the settings used,
    the final loss terms and the fit's wall time."""

    result: np.ndarray
    model_only: np.ndarray | None
    settings: Settings
    loss: dict[str, float]
    seconds: float


class VisibleL1:
    """Mean absolute difference to ``target`` over the visible entries (the fit's objective)."""

    def __init__(self, target: torch.Tensor, visible: torch.Tensor):
        self.index = visible.nonzero().squeeze(1)
        self.target = target[self.index]

    def prepare(self, vertices: torch.Tensor, iteration: int) -> None:
        """Nothing to precompute."""

    def reset(self) -> None:
        """Nothing is kept between calls."""

    def __call__(self, vertices: torch.Tensor) -> dict[str, torch.Tensor]:
        # index_select: its backward is deterministic, advanced indexing's is not with several threads.
        return {"data": (vertices.index_select(0, self.index) - self.target).abs().mean()}


def inpaint_settings(method: str, iterations: int | None = None, lr: float | None = None, beta: float | None = None,
                     lam: float | None = None) -> Settings:
    """The tuned settings of ``method`` for inpainting (:data:`statfit.core.methods.METHODS`) with the given
    values replaced (validated)."""
    (settings,) = resolve(method, job="inpaint", iterations=iterations, lr=lr, beta=beta, lam=lam)
    return settings


def check_inputs(image: np.ndarray, visible: np.ndarray, charts: np.ndarray | None = None) -> None:
    """Refuse an image, mask or chart image the fit cannot use, with a message naming the problem."""
    if image.ndim != 3 or image.shape[-1] not in (1, 3, 4):
        raise StatfitError(f"the image must have shape (H, W, C) with C = 1, 3 or 4, got {image.shape}")
    if not np.isfinite(image).all():
        raise StatfitError("the image has NaN or infinite values")
    for name, other in (("mask", visible), ("chart image", charts)):
        if other is not None and other.shape != image.shape[:2]:
            raise StatfitError(f"the {name} is {other.shape[1]}×{other.shape[0]} but the image is "
                               f"{image.shape[1]}×{image.shape[0]}")
    if not visible.any():
        raise StatfitError("the mask has no visible pixel (white = visible; --mask-invert swaps)")


def check_model(model: TextureModel | None, image: np.ndarray, method: str) -> None:
    """Refuse a missing model for a model method, or a model of another size or channel count."""
    if model is None:
        if METHODS[method].needs_model:
            raise StatfitError(f"method {method!r} needs a texture model (--model)")
        return
    if model.size != image.shape[:2]:
        raise StatfitError(f"the model is {model.width}×{model.height} but the image is {image.shape[1]}×"
                           f"{image.shape[0]}; pass --resize to fit at the model's size")
    if model.channels != image.shape[-1]:
        raise StatfitError(f"the model has {model.channels} channel(s) but the image has {image.shape[-1]}")


def model_reconstruction(model: TextureModel, image: np.ndarray, visible: np.ndarray,
                         device: str | torch.device = "cpu") -> np.ndarray:
    """The model's MAP texture (H, W, C) given the visible pixels: coefficients c ~ N(0, I), pixel
    noise ``PROJECTION_NOISE``; ``(BᵥᵀBᵥ + σ²I) c = Bᵥᵀ(y − x̄)`` with B = U diag(std)."""
    basis_t = torch.as_tensor(model.basis_t, device=device)
    std = torch.as_tensor(model.std, dtype=torch.float64, device=device)
    mean = torch.as_tensor(model.mean.reshape(-1), device=device)
    weight = torch.as_tensor(np.repeat(visible.reshape(-1), model.channels), dtype=basis_t.dtype, device=device)
    residual = torch.as_tensor(image.reshape(-1), dtype=basis_t.dtype, device=device) - mean
    masked = basis_t * weight
    gram = (masked @ basis_t.T).double() * std[:, None] * std[None, :]
    rhs = (masked @ residual).double() * std
    prior = PROJECTION_NOISE**2 * torch.eye(len(std), dtype=torch.float64, device=device)
    coeffs = torch.linalg.solve(gram + prior, rhs)
    flat = mean + (coeffs * std).to(basis_t.dtype) @ basis_t
    return flat.reshape(image.shape).cpu().numpy()


def inpaint(image: np.ndarray, visible: np.ndarray, method: str | None = None, model: TextureModel | None = None, *,
            settings: Settings | None = None, start: str = "mean", charts: np.ndarray | None = None,
            resize: bool = False, device: str | torch.device | None = None, on_record: Progress | None = None) -> Inpainting:
    """Fill the holes (``visible`` False) of ``image`` (H, W, C) in [0, 1].

    ``method``: hybrid (default with a model), statistical, pca, laplacian (default without), none;
    ``settings`` override ``INPAINT_DEFAULTS``; ``charts`` (H, W) UV-chart labels restrict the
    Laplacian (:func:`statfit.texture.grid.grid_laplacian`). ``start``: the fit starts from the
    model's mean (``mean``, measured best) or its reconstruction from the visible pixels
    (``reconstruction``); without a model, from the visible pixels' mean colour. With ``resize``, an
    image of another size than the model's is resampled to it for the fit, and the filled holes
    are resampled back (the result has the input's size; its visible pixels stay the input's).
    """
    method = method or (settings.method if settings else ("hybrid" if model is not None else "laplacian"))
    settings = settings or inpaint_settings(method)
    if settings.method != method:
        raise StatfitError(f"settings are for {settings.method!r}, not {method!r}")
    image = np.asarray(image, dtype=np.float32)
    visible = np.asarray(visible, dtype=bool)
    check_inputs(image, visible, charts)
    if start not in STARTS:
        raise StatfitError(f"unknown start {start!r}; choose one of {', '.join(STARTS)}")
    if resize and model is not None and model.size != image.shape[:2]:
        labels = None if charts is None else resize_labels(charts, model.size)
        fitted = inpaint(resize_image(image, model.size), resize_mask(visible, model.size), method, model,
                         settings=settings, start=start, charts=labels, device=device, on_record=on_record)
        filled = resize_image(fitted.result, image.shape[:2])
        return replace(fitted, result=np.where(visible[..., None], image, filled),
                       model_only=resize_image(fitted.model_only, image.shape[:2]))
    check_model(model, image, method)
    device = resolve_device(device)
    height, width, channels = image.shape
    target = torch.as_tensor(image.reshape(-1, channels), device=device)
    if model is not None:
        model_only = model_reconstruction(model, image, visible, device)
        space = FitSpace(torch.as_tensor(model.mean, device=device), torch.as_tensor(model.basis_t, device=device),
                         torch.as_tensor(model.std, dtype=torch.float32, device=device), None)
        x0 = torch.as_tensor((model_only if start == "reconstruction" else model.mean).reshape(-1, channels),
                             device=device)
    else:
        model_only = None
        x0 = target[torch.as_tensor(visible.reshape(-1), device=device)].mean(dim=0).expand_as(target).contiguous()
        empty = torch.zeros((0, target.numel()), device=device)
        space = FitSpace(x0, empty, torch.zeros(0, device=device), None)
    if method in ("laplacian", "hybrid"):
        space = replace(space, laplacian_matrix=grid_laplacian(height, width, charts))
    objective = VisibleL1(target, torch.as_tensor(visible.reshape(-1), device=device))
    started = time.perf_counter()
    fit = run_stages((settings,), space, objective, x0, on_record=on_record)
    filled = fit.vertices.detach().reshape(image.shape).cpu().numpy()
    _check_not_runaway(image[visible], filled[~visible])
    result = np.where(visible[..., None], image, filled).astype(np.float32)
    return Inpainting(result, model_only, settings, fit.loss, time.perf_counter() - started)


def _check_not_runaway(seen: np.ndarray, holes: np.ndarray) -> None:
    """Raise DivergenceError where the fill's hole colours ``holes`` (H', C) lie, at the median,
    more than RUNAWAY_COLOUR times the range of the ``seen`` colours (V, C) beyond it; an image
    without a hole (or without a seen pixel) tests nothing."""
    if not (len(seen) and len(holes)):
        return
    low, high = float(seen.min()), float(seen.max())
    beyond = float(np.median(np.maximum(np.maximum(low - holes, holes - high), 0.0))) / max(high - low, 1.0)
    if not beyond <= RUNAWAY_COLOUR:
        raise DivergenceError(f"the fill diverged: its colours lie {beyond:.3g} times the seen colours' range "
                              "beyond it (median; step size too large?)")
