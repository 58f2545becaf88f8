"""Splatting on a mesh: fit a model's template, with 2D Gaussian surfels bound to its triangles, to
photographs from calibrated cameras. The library entry point of ``statfit splat``.

The vertices go through the method's parametrisation (statistical, hybrid, laplacian, pca, none:
the same filters and fitting loop as every job); the splats' colours, opacities, scales and
in-plane angles are the objective's own parameters (:mod:`statfit.objectives.images`). The fit
runs in the model's unit frame; the cameras must be in the model's frame and units (as
``statfit synth views`` writes them): a camera that does not see the model is refused. Splat
colours start from the photographs (each splat takes the pixel under its centre in the view
that faces it most squarely). Held-out ('test') views are never fitted; they are scored after
the fit (PSNR, SSIM).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import torch

from statfit.geometry.align import Similarity
from statfit.structures.camera import Camera
from statfit.core.device import resolve_device
from statfit.errors import StatfitError
from statfit.core.fit import StageTimer
from statfit.structures.frame import Frame
from statfit.io.splats import COLOURS, RECORD
from statfit.core.methods import resolve
from statfit.model.statmodel import StatModel
from statfit.objectives.images import ImageObjective, TrainingView, psnr, ssim
from statfit.objectives.weights import MASK_WEIGHT
from statfit.core.pose import camera_in_frame
from statfit.core.settings import FitSpace, Settings
from statfit.renderer import MeshSplats, render_surfels
from statfit.core.runaway import check_not_runaway
from statfit.core.stages import Fit, run_stages
from statfit.core.threads import choose_threads, intra_op_threads
from statfit.structures.views import View

# Floats the splat renderer touches per pixel and iteration (for the thread choice).
SPLAT_FLOATS_PER_PIXEL = 64
# Probabilities are kept this far from 0 and 1 before their logit is taken.
PROBABILITY_MARGIN = 1e-6
MIN_VISIBLE_FRACTION = 0.5  # of the template's vertices, in front of a camera and inside its image


@dataclass
class SplatFit:
    """The fitted mesh (``fit``), the splats on it, and per-view scores: ``scores[name]`` =
    {'split', 'psnr', 'ssim'} of the splats rendered at the fit against the photograph."""

    fit: Fit
    splats: MeshSplats
    scores: dict[str, dict[str, Any]]

    def mean_scores(self, split: str) -> dict[str, float] | None:
        """Mean PSNR and SSIM over the views of ``split`` (None: no such view)."""
        chosen = [s for s in self.scores.values() if s["split"] == split]
        if not chosen:
            return None
        return {"psnr": float(np.mean([s["psnr"] for s in chosen])),
                "ssim": float(np.mean([s["ssim"] for s in chosen])), "views": len(chosen)}


def splat_stages(method: str = "default", preset: str = "tuned", **overrides: Any) -> tuple[Settings, ...]:
    """The stages of ``method`` for splatting."""
    return resolve(method, preset, job="splat", **overrides)


def check_views_see(template: np.ndarray, views: list[View]) -> None:
    """Refuse views whose camera sees less than half of the template (another frame or units?)."""
    points = torch.as_tensor(template, dtype=torch.float64)
    for view in views:
        pixels, depth = view.camera.project(points)
        inside = ((depth > 0) & (pixels[:, 0] >= 0) & (pixels[:, 0] < view.camera.width)
                  & (pixels[:, 1] >= 0) & (pixels[:, 1] < view.camera.height))
        if float(inside.double().mean()) < MIN_VISIBLE_FRACTION:
            raise StatfitError(f"view {view.name}: its camera sees {100 * float(inside.double().mean()):.0f}% of the "
                               "model: are the cameras in the model's frame and units?")


def starting_colours(splats: MeshSplats, vertices: torch.Tensor, views: list[TrainingView]) -> torch.Tensor:
    """Colour logits (P, 3): each splat's colour is the pixel under its centre in the view whose
    camera its normal faces most squarely (occlusion is ignored; the fit corrects the rest)."""
    with torch.no_grad():
        surfels = splats.surfels(vertices)
        normals = torch.linalg.cross(surfels.tangent_u, surfels.tangent_v, dim=1)
        facing = torch.stack([((view.camera.center.to(vertices) - surfels.centres) * normals).sum(dim=1)
                              / (view.camera.center.to(vertices) - surfels.centres).norm(dim=1)
                              for view in views])                                     # (V, P)
        best = facing.argmax(dim=0)
        colours = torch.empty_like(surfels.colours)
        for index, view in enumerate(views):   # one vectorised lookup per view
            chosen = torch.nonzero(best == index).squeeze(1)
            pixels, _ = view.camera.project(surfels.centres.index_select(0, chosen))
            col = pixels[:, 0].long().clamp(0, view.camera.width - 1)
            row = pixels[:, 1].long().clamp(0, view.camera.height - 1)
            colours[chosen] = view.image[row, col]
        colours = colours.clamp(0.02, 0.98)
        return torch.log(colours / (1 - colours))


def fit_views(model: StatModel, views: list[View], method: str = "default", *, preset: str = "tuned",
              per_triangle: int = 1, views_per_step: int = 1, mask_weight: float = MASK_WEIGHT,
              device: str | None = None, dtype: torch.dtype = torch.float32, seed: int = 0,
              on_record: Callable[[int, dict[str, float]], None] | None = None,
              on_snapshot: Callable[[int, np.ndarray], None] | None = None, timer: StageTimer | None = None,
              stages: tuple[Settings, ...] | None = None, threads: int | None = None,
              **overrides: Any) -> SplatFit:
    """Fit ``model``, with ``per_triangle`` splats on each triangle, to the 'train' ``views``.

    ``views_per_step``: views rendered per iteration; ``mask_weight``: weight of the mask term
    (views with a mask); ``on_snapshot(iteration, vertices)`` gets the vertices (N, 3, world)
    every 10 iterations; ``threads``: torch intra-op threads (default: chosen from the sizes).
    ``overrides`` replace the method's settings (:func:`statfit.core.methods.resolve`); ``stages``
    replaces the method by an explicit pipeline.
    """
    train = [view for view in views if view.split == "train"]
    if not train:
        raise StatfitError("no training view: every view is held out")
    if not (np.isfinite(mask_weight) and mask_weight >= 0):
        raise StatfitError(f"mask_weight must be a finite number ≥ 0, got {mask_weight}")
    if isinstance(views_per_step, bool) or not 1 <= views_per_step <= len(train):
        raise StatfitError(f"views per step must be from 1 to the {len(train)} training views, got {views_per_step}")
    stages = stages or splat_stages(method, preset, **overrides)
    check_views_see(model.template, views)
    torch_device = resolve_device(device, "splat")
    work = model.basis.size + SPLAT_FLOATS_PER_PIXEL * train[0].image.shape[0] * train[0].image.shape[1]
    threads = choose_threads(work, threads)
    with intra_op_threads(threads):
        torch.manual_seed(seed)
        started = time.perf_counter()
        frame = model.frame
        space = FitSpace.of(model, frame, torch_device, dtype)
        faces = torch.as_tensor(model.faces, dtype=torch.long, device=torch_device)
        x0 = torch.as_tensor(frame.to_unit(model.template), dtype=dtype, device=torch_device)
        converted = [_training_view(view, frame, dtype, torch_device) for view in views]
        training = [done for done, view in zip(converted, views) if view.split == "train"]
        splats = MeshSplats.on(faces, per_triangle, dtype=dtype)
        with torch.no_grad():
            splats.colour_logit.copy_(starting_colours(splats, x0, training))
        objective = ImageObjective(training, splats, views_per_step=views_per_step, mask_weight=mask_weight,
                                   seed=seed)
        timer = timer or StageTimer.for_device(torch_device)

        def to_world(x: torch.Tensor) -> np.ndarray:
            return frame.from_unit(x.detach().cpu().double().numpy())

        snapshot = None if on_snapshot is None else lambda it, x: on_snapshot(it, to_world(x))
        result = run_stages(stages, space, objective, x0, on_record=on_record, on_snapshot=snapshot, timer=timer)
        for view in training:       # against the photograph's foreground, or its whole image where it has no mask
            silhouette = torch.ones(view.image.shape[:2], dtype=torch.bool) if view.mask is None else view.mask > 0.5
            check_not_runaway(x0, result.vertices, view.camera, silhouette.cpu().numpy())
        scores = score_views(splats, result.vertices, converted, views)
        fit = Fit(to_world(result.vertices), Similarity(), stages, result.loss, time.perf_counter() - started,
                  dict(timer.seconds), result.iterations, threads=threads)
        return SplatFit(fit, splats, scores)


def score_views(splats: MeshSplats, vertices: torch.Tensor, rendered_views: list[TrainingView],
                views: list[View]) -> dict[str, dict[str, Any]]:
    """PSNR and SSIM of the splats on ``vertices`` against each view's photograph."""
    scores = {}
    with torch.no_grad():
        surfels = splats.surfels(vertices)
        for training, view in zip(rendered_views, views):
            image = render_surfels(surfels, training.camera).colour.clamp(0, 1)
            scores[view.name] = {"split": view.split, "psnr": psnr(image, training.image),
                                 "ssim": float(ssim(image, training.image))}
    return scores


def _training_view(view: View, frame: Frame, dtype: torch.dtype, device: torch.device) -> TrainingView:
    mask = None if view.mask is None else torch.as_tensor(view.mask, dtype=dtype, device=device)
    return TrainingView(camera_in_frame(view.camera, frame), torch.as_tensor(view.image, dtype=dtype, device=device),
                        mask)


def splat_records(splats: MeshSplats, vertices: np.ndarray) -> np.ndarray:
    """The splats (3 colour channels) on the mesh ``vertices`` (N, 3) as file records (P,)
    (:data:`statfit.io.splats.RECORD`): world centre and normal, the binding, colours, opacity."""
    if splats.colour_logit.shape[1] != 3:
        raise StatfitError(f"splat files hold RGB splats; these have {splats.colour_logit.shape[1]} colour channels")
    with torch.no_grad():
        surfels = splats.surfels(torch.as_tensor(vertices, dtype=splats.barycentric.dtype, device=splats.faces.device))
        normal = torch.linalg.cross(surfels.tangent_u, surfels.tangent_v, dim=1)
        columns = {"triangle": splats.triangle, "angle": splats.angle, "opacity": surfels.opacity}
        for axis, name in enumerate("xyz"):
            columns[name], columns[f"n{name}"] = surfels.centres[:, axis], normal[:, axis]
        for k in range(3):
            columns[f"bary_{k}"] = splats.barycentric[:, k]
            columns[COLOURS[k]] = surfels.colours[:, k]
        for k in range(2):
            columns[f"log_scale_{k}"] = splats.log_scale[:, k]
    records = np.empty(len(splats), dtype=RECORD)
    for name, column in columns.items():
        records[name] = column.detach().cpu().numpy()
    return records


def splats_from_records(records: np.ndarray, faces: torch.Tensor, dtype: torch.dtype = torch.float32) -> MeshSplats:
    """MeshSplats from checked file ``records`` (P,), bound to ``faces`` (F, 3) long; the free
    tensors are ``dtype`` leaves that require grad, on ``faces.device``."""
    def columns(*names: str) -> np.ndarray:
        return np.stack([records[name].astype(np.float64) for name in names], axis=-1)

    def logit(p: np.ndarray) -> np.ndarray:
        p = np.clip(p, PROBABILITY_MARGIN, 1 - PROBABILITY_MARGIN)
        return np.log(p / (1 - p))

    def leaf(values: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(values, dtype=dtype, device=faces.device).requires_grad_(True)

    triangle = torch.as_tensor(records["triangle"].astype(np.int64), device=faces.device)
    return MeshSplats(faces, triangle, torch.as_tensor(columns("bary_0", "bary_1", "bary_2"), dtype=dtype,
                                                       device=faces.device),
                      leaf(records["angle"].astype(np.float64)), leaf(columns("log_scale_0", "log_scale_1")),
                      leaf(logit(columns(*COLOURS))), leaf(logit(records["opacity"].astype(np.float64))))


def render_splats(splats: MeshSplats, vertices: np.ndarray, camera: Camera, dtype: torch.dtype = torch.float32
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The splats on the mesh ``vertices`` (N, 3, world) seen by ``camera``: colour (H, W, 3) over
    black and alpha (H, W), float32 (the splats' scales follow the triangles, so any frame works)."""
    with torch.no_grad():
        surfels = splats.surfels(torch.as_tensor(vertices, dtype=dtype, device=splats.faces.device))
        image = render_surfels(surfels, camera)
    return image.colour.clamp(0, 1).cpu().numpy(), image.alpha.cpu().numpy()
