"""Many normal maps fitted with one model in one program: the fits' gradient stages stepped together.

:func:`reconstruct_many` fits each map as :func:`statfit.render.job.reconstruct` would: its own
checks, alignment (pose search) and data term. The stages of all the fits of one image size then
run as one (:mod:`statfit.core.together`): vertices (B, N, 3), one filter product for all B, one
renderer that draws the B meshes into B images stacked (:class:`statfit.renderer.steady.SteadyRenderer`
with B cameras), one data term whose views are normalised each by its own counts. So a fitting
iteration launches about the ops of one fit whatever B: on a GPU, where a render iteration is
launch-bound, B fits cost little more than one.

A view's term and its gradient are those of its own objective (to float rounding: the sums run in
another order), and nothing is shared between the fits but the program, so a fit made together
follows the fit made alone (docs/benchmarks.md §15). A fit that fails (a map refused, a framing
refused, a divergence) fails alone: a batched stage that fails is rerun a fit at a time.
"""
from __future__ import annotations

from typing import Any, Sequence

import torch

from statfit.core.device import resolve_device
from statfit.core.settings import Settings
from statfit.core.stages import PipelineResult
from statfit.core.threads import choose_threads, intra_op_threads
from statfit.core.together import FitOutcome, Member, fits_in_memory, run_stages_together
from statfit.errors import StatfitError
from statfit.model.cut import fitting_model_and_rule
from statfit.model.statmodel import StatModel
from statfit.objectives.normals import NormalMapObjective
from statfit.objectives.weights import SILHOUETTE_WEIGHT
from statfit.render.job import RENDER_FLOATS_PER_PIXEL, PosedView, checked_stages, posed_view, silhouette_sides
from statfit.render.visibility import visibility_options
from statfit.renderer import Camera
from statfit.structures.normal_map import NormalMap


def together_for(model: StatModel, pixels: int, device: torch.device) -> int:
    """How many normal maps of ``pixels`` pixels a batch worker fits together by default: 1 on a
    CPU (the bytes of ``statfit render``; fits together take 0.96× the time there: docs/benchmarks.md
    §15); on a GPU as many as fit its memory (:func:`statfit.core.together.fits_in_memory` of
    :func:`bytes_per_fit`)."""
    return fits_in_memory(bytes_per_fit(model, pixels), device) if device.type == "cuda" else 1


def bytes_per_fit(model: StatModel, pixels: int) -> int:
    """A generous bound on one fit's memory in a stage stepped together (float32): 40 copies of its
    vertices (parameters, moments, gradients, filter products, vertex normals) and 800 bytes per
    pixel (the renderer's per-pixel keys, indices and normals, and what the backward pass keeps).
    Measured on a CPU: 140 MB a fit for ICT's head at 512² (4 fits at once against one: 984 against
    562 MB at the peak), ~530 bytes a padded pixel."""
    return 4 * 40 * 3 * model.num_vertices + 800 * pixels


class _View(Member):
    """A normal map's fit among many: besides a member's, its posed view."""

    def __init__(self, index: int):
        super().__init__(index)
        self.view: PosedView | None = None


def reconstruct_many(model: StatModel, normal_maps: Sequence[NormalMap], cameras: Sequence[Camera],
                     method: str = "default", *, preset: str = "tuned", normal_space: str = "world",
                     normal_convention: str = "opencv", align: str = "rigid", device: str | None = None,
                     dtype: torch.dtype = torch.float32, silhouette_weight: float = SILHOUETTE_WEIGHT, seed: int = 0,
                     stages: tuple[Settings, ...] | None = None, region: str | None = None,
                     threads: int | None = None, silhouette: str = "auto", rigid_modes: str = "auto",
                     **overrides: Any) -> list[FitOutcome]:
    """Fit ``model`` to each of ``normal_maps`` seen by its camera (``cameras``, one per map), with the
    options of :func:`statfit.render.job.reconstruct`; the stages of the fits of one image size
    stepped together. One :class:`statfit.core.together.FitOutcome` per map, in order; a bad option
    raises StatfitError (it would fail every fit)."""
    if len(cameras) != len(normal_maps):
        raise StatfitError(f"{len(normal_maps)} normal maps but {len(cameras)} cameras")
    model, place_rule = fitting_model_and_rule(model, rigid_modes, finds_pose=align != "none")
    stages = checked_stages(model, align, silhouette, silhouette_weight, stages, method, preset, region, overrides)
    torch_device = resolve_device(device, "render")
    largest = max((each.mask.size for each in normal_maps), default=0)
    threads = choose_threads(model.basis.size + RENDER_FLOATS_PER_PIXEL * largest, threads)
    members = [_View(i) for i in range(len(normal_maps))]
    options = dict(normal_space=normal_space, normal_convention=normal_convention, align=align,
                   silhouette_weight=silhouette_weight, silhouette=silhouette_sides(silhouette, model), region=region,
                   **visibility_options(preset, torch_device))
    with intra_op_threads(threads):
        torch.manual_seed(seed)
        for member, normal_map, camera in zip(members, normal_maps, cameras):
            member.view = member.alone(posed_view, model, place_rule, normal_map, camera, torch_device, dtype,
                                       **options, timer=member.timer)
            if member.view is not None:
                member.space, member.objective, member.x = member.view.space, member.view.objective, member.view.start
        groups: dict[tuple, list[_View]] = {}   # one image size and one model's modes a group
        for member in members:
            if not member.failed:
                groups.setdefault((*member.view.mask.shape, member.view.rigid_free), []).append(member)
        for group in groups.values():
            run_stages_together(group, stages, _view_batch)
        for member in members:
            if not member.failed:
                result = PipelineResult(member.x, member.loss, member.done)
                member.outcome.fit = member.alone(member.view.fitted, result, stages, member.seconds, member.timer,
                                                  threads)
    return [m.outcome for m in members]


def _view_batch(members: Sequence[_View], settings: Settings) -> NormalMapObjective:
    """The data term of ``members`` (views of one image size) stepped together."""
    views = [m.view for m in members]
    return NormalMapObjective(torch.stack([v.target for v in views]), torch.stack([v.mask for v in views]),
                              [v.camera for v in views], **views[0].options)
