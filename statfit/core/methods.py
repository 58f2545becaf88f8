"""The registry of fitting methods: one entry per method, with how to build it and its settings.

A method turns (settings, the model's fit space, start vertices) into a parametrisation and an
optimiser (:func:`build`); its entry also holds the paper's settings and our tuned settings for
each job it serves (``register``, ``render``, ``inpaint``). A *pipeline* is a sequence of stages,
each starting where the last ended; the ``default`` pipelines are the ones our studies chose
(docs/studies.md). Adding a method is one :class:`Method` passed to :func:`add_method`
(docs/method.md, "Adding a method").
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from importlib import metadata
from typing import Any, Callable

import torch

from statfit.errors import StatfitError
from statfit.core.method_help import LANDMARK_WEIGHT, PCA_LANDMARK_WEIGHT, SUMMARIES
from statfit.core.filters import HybridFilter, IdentityFilter, LaplacianFilter, StatisticalFilter
from statfit.core.fit import Parametrization
from statfit.core.optim import Adam, Optimizer, UniformAdam
from statfit.core.parametrize import Filter, FilteredVertices, PCACoefficients, RegularizedVertices
from statfit.core.settings import MAX_ITERATIONS, FitSpace, Settings, check_int

JOBS = ("register", "render", "inpaint", "splat")
# The paper's iteration counts per job: 500 for scan registration, 3000 for inverse rendering.
PAPER_ITERATIONS = {"register": 500, "render": 3000}
# The Gauss–Newton pca stage stops by itself (31–50 iterations on the study's cases, docs/studies.md
# §9); this only bounds it.
GAUSS_NEWTON_ITERATIONS = 200
SPLAT_ITERATIONS = 400

Builder = Callable[[Settings, FitSpace, torch.Tensor], tuple[Parametrization, Optimizer]]


@dataclass(frozen=True)
class Method:
    """A fitting method: ``build`` makes its parametrisation and optimiser; ``paper`` is the
    paper's setting (None: not in the paper); ``tuned`` our setting per job (a job without one
    does not offer the method); ``needs_model``: whether it uses the model's modes;
    ``landmark_weight``: its landmark term's weight when registering with landmarks."""

    name: str
    build: Builder
    tuned: dict[str, Settings]
    paper: Settings | None = None
    needs_model: bool = True
    summary: str = ""
    landmark_weight: float = LANDMARK_WEIGHT


def filtered_method(make_filter: Callable[[Settings, FitSpace, torch.Tensor], Filter]) -> Builder:
    """The builder of a filtered method, ``x = x0 + F u`` with UniformAdam on u; ``x0`` (N, 3), or
    (B, N, 3) for B fits at once (each with its own step scale)."""
    def build(settings: Settings, space: FitSpace, x0: torch.Tensor):
        param = FilteredVertices(x0, make_filter(settings, space, x0[0] if x0.dim() == 3 else x0))
        return param, UniformAdam(param.parameters(), lr=settings.lr, betas=settings.adam_betas, fits=x0.dim() == 3,
                                  steps=settings.iterations, settle=settings.settle)

    return build


def mode_gains(settings: Settings, space: FitSpace) -> torch.Tensor | None:
    """The filter's gain per mode, (std_j / std_1)^γ, or None for γ = 0 (gain 1 on every mode)."""
    return (space.std / space.std[0]) ** settings.mode_gain if settings.mode_gain else None


def statistical_filter(settings: Settings, space: FitSpace, x0: torch.Tensor) -> Filter:
    return StatisticalFilter(space.basis_t, settings.beta, settings.power, mode_gains(settings, space))


def laplacian_filter(settings: Settings, space: FitSpace, x0: torch.Tensor) -> LaplacianFilter:
    if space.laplacian_matrix is not None:
        return LaplacianFilter.from_laplacian(space.laplacian_matrix, settings.lam, settings.solver, x0.dtype,
                                              x0.device)
    return LaplacianFilter(x0.detach().cpu().double().numpy(), space.faces, settings.lam, settings.laplacian,
                           settings.solver, x0.dtype, x0.device)


def hybrid_filter(settings: Settings, space: FitSpace, x0: torch.Tensor) -> Filter:
    return HybridFilter(space.basis_t, settings.beta, laplacian_filter(settings, space, x0), settings.power,
                        mode_gains(settings, space))


def _pca(settings: Settings, space: FitSpace, x0: torch.Tensor):
    scaled = space.basis_t * space.std[:, None]
    start = torch.mv(space.basis_t, (x0 - space.mean).reshape(-1)) / space.std
    param = PCACoefficients(space.mean, scaled, start, settings.prior)
    return param, Adam(param.parameters(), lr=settings.lr, betas=settings.adam_betas)


def _regularized(settings: Settings, space: FitSpace, x0: torch.Tensor):
    param = RegularizedVertices(x0, space.mean, space.basis_t, settings.beta)
    return param, UniformAdam(param.parameters(), lr=settings.lr, betas=settings.adam_betas,
                              steps=settings.iterations, settle=settings.settle)


def _none(settings: Settings, space: FitSpace, x0: torch.Tensor):
    param = FilteredVertices(x0, IdentityFilter())
    return param, Adam(param.parameters(), lr=settings.lr, betas=settings.adam_betas)


METHODS: dict[str, Method] = {}
# Other packages add methods by naming a module under this entry-point group; it calls add_method.
PLUGIN_GROUP = "statfit.methods"
_plugins: list[str] = []


def add_method(method: Method) -> None:
    """Register ``method`` under its name (replacing one of the same name)."""
    for job in method.tuned:
        if job not in JOBS:
            raise StatfitError(f"method {method.name!r}: unknown job {job!r}; choose one of {', '.join(JOBS)}")
    METHODS[method.name] = method


def load_plugins() -> list[str]:
    """Import, once, every module declared under the ``statfit.methods`` entry-point group (each
    registers its methods); returns their names."""
    if not _plugins:
        _plugins.append(PLUGIN_GROUP)  # loaded (even if none is installed)
        for entry in metadata.entry_points(group=PLUGIN_GROUP):
            try:
                entry.load()
            except Exception as error:  # a broken plugin must not break the built-in methods
                raise StatfitError(f"the statfit.methods plugin {entry.name!r} ({entry.value}) failed to load: "
                                   f"{error}") from error
            _plugins.append(entry.name)
    return _plugins[1:]


# Tuned settings: each method's best in our studies (docs/studies.md: §1 registration on ICT partial
# scans with expressions outside the model, §5 rendering, §9 the Gauss–Newton pca; inpainting:
# docs/method.md, "Texture inpainting"). Texture defaults are the paper's lr, β and λ (β = 100 was
# ≤ 1.3% better on faces, equal on digits; λ = 19 the Laplacian's best on both; 1000 iterations
# were slightly worse than 300).
for _method in (
    Method("statistical", filtered_method(statistical_filter), summary=SUMMARIES["statistical"],
           paper=Settings("statistical", 500, 0.01, beta=30.0),
           tuned={"register": Settings("statistical", 1000, 0.05, beta=1000.0, mode_gain=1.0),
                  "render": Settings("statistical", 3000, 0.01, beta=1000.0, mode_gain=1.0),
                  "inpaint": Settings("statistical", 300, 0.01, beta=30.0),
                  "splat": Settings("statistical", SPLAT_ITERATIONS, 0.05, beta=1000.0, mode_gain=1.0)}),
    Method("laplacian", filtered_method(laplacian_filter), needs_model=False,
           summary=SUMMARIES["laplacian"],
           paper=Settings("laplacian", 500, 0.01, lam=19.0),
           # register's: also the default's fallback refit; its step settles over the last half, so a
           # nudge of the scan no scanner could see no longer sends the fit elsewhere (docs/studies.md §30)
           tuned={"register": Settings("laplacian", 1000, 0.1, lam=300.0, settle=0.5),
                  "render": Settings("laplacian", 3000, 0.003, lam=19.0),
                  "inpaint": Settings("laplacian", 300, 0.01, lam=19.0),
                  "splat": Settings("laplacian", SPLAT_ITERATIONS, 0.003, lam=19.0)}),
    Method("hybrid", filtered_method(hybrid_filter), summary=SUMMARIES["hybrid"],
           paper=Settings("hybrid", 500, 0.01, beta=30.0, lam=19.0),
           tuned={"register": Settings("hybrid", 1000, 0.03, beta=30.0, lam=19.0),
                  "render": Settings("hybrid", 3000, 0.01, beta=30.0, lam=19.0, mode_gain=1.0),
                  "inpaint": Settings("hybrid", 300, 0.01, beta=30.0, lam=19.0),
                  "splat": Settings("hybrid", SPLAT_ITERATIONS, 0.01, beta=30.0, lam=19.0, mode_gain=1.0)}),
    Method("pca", _pca, summary=SUMMARIES["pca"],
           paper=Settings("pca", 500, 5.0),
           tuned={"register": Settings("pca", GAUSS_NEWTON_ITERATIONS, 0.0, optimizer="gauss-newton", noise=0.003),
                  "render": Settings("pca", 3000, 0.05),
                  "inpaint": Settings("pca", 300, 0.01),
                  "splat": Settings("pca", SPLAT_ITERATIONS, 0.05)},
           landmark_weight=PCA_LANDMARK_WEIGHT),
    Method("regularized", _regularized, summary=SUMMARIES["regularized"],
           paper=Settings("regularized", 500, 0.01, beta=10.0),
           tuned={"register": Settings("regularized", 1000, 0.1, beta=30.0),
                  "render": Settings("regularized", 3000, 0.01, beta=10.0)}),
    Method("none", _none, needs_model=False, summary=SUMMARIES["none"],
           paper=Settings("none", 500, 0.01),
           tuned={"register": Settings("none", 1000, 0.003),
                  "render": Settings("none", 3000, 0.001),
                  "inpaint": Settings("none", 300, 0.01),
                  "splat": Settings("none", SPLAT_ITERATIONS, 0.001)}),
):
    add_method(_method)


@dataclass(frozen=True)
class Fallback:
    """Refit with ``method`` (its tuned settings) where a pipeline's fit cannot be this model's
    person: it leaves the scan points it was given more than ``residual`` from its surface on
    average, in the fitted model's RMS radii (the fit frame's unit), or its shape's code in the
    model has an RMS over the modes above ``code`` standard deviations (a person of the model has
    about 1). Its prior then guesses the unseen part worse than a smooth fit does (docs/studies.md §23)."""

    method: str
    residual: float
    code: float = float("inf")


@dataclass(frozen=True)
class Pipeline:
    """Stages run in order, each from where the last ended; ``fallback``: what replaces the fit
    where it cannot explain the scan (register only)."""

    stages: tuple[Settings, ...]
    summary: str = ""
    landmark_weight: float = LANDMARK_WEIGHT
    fallback: Fallback | None = None


# register's fallback: a default fit that leaves the scan points it was given 2% of the model's RMS
# radius away on average (~1.9 mm on a head), or whose shape needs 3.5 standard deviations per mode
# (RMS; a person of the model needs about 1), met a person its model cannot make. Both chosen on ICT,
# in family: round thresholds above every in-family case's value (residual: 1.48% at most, a scan
# half clutter; code: 2.94, §15's half faces of people outside the 50 modes fitted), so no ICT study
# result moves; checked across families (docs/studies.md §23).
FALLBACK_RESIDUAL = 0.02
FALLBACK_CODE = 3.5
# ... the residual leaving out the points whose nearest surface point lies within this many radii of
# the model's open border (a face mask's neck and shoulders, under and behind its chin, fired the gate
# on 5 of the 9 neck scans of docs/studies.md §34). Chosen there, on face masks: the narrowest of 0.05, 0.1
# and 0.2 that leaves every neck scan under half the threshold (0.77%; 0.05: 1.93%). Checked across
# families (§35): no in-family residual crosses 2%, and §17's and §19's errors fall.
FALLBACK_BORDER_BAND = 0.1


# register: the closed-form coefficients (Gauss–Newton with continuation) find the shape in the
# model's span in ~1 s — ending at its prior's last level (σ 0.003) or the one before (0.0095),
# whichever predicts the scan's edge that faces what it does not show (docs/studies.md §32: held-out
# halves 12% closer in family, 1% across) — without the landmark term, which a converged solve meets
# by bending what the scan does not show (§15) — then 200 UniformAdam steps of the hybrid filter with
# β = 1 (half of each step in the span, half smooth motion off it) bend the mesh to what the span
# cannot make: lower error than the former 5,333 statistical steps on all nine study cases, in and
# off the span, at a tenth of the time (docs/studies.md §9). Its step, 0.03, travels far enough in
# 200 steps for landmarks to open a jaw the span cannot (§12: 0.39x the start-only landmark error,
# where 0.006 reached 0.66x) for +0.6% in-span error. render: the hybrid filter with mode
# gains (γ = 1), β 30 for 150 iterations then β 10 for 300 at a 5× larger step than the 3,000-iteration
# methods (β 10's off-model gain, 1/11 instead of 1/31, lets the expression in; §11), then 600
# iterations of the Laplacian filter (lr 0.01), which fits the detail no span holds. From the rigid
# alignment's converged coefficients (SHAPE_LR) it is the lowest all-vertex error on all six held-out
# bodies and lower unseen error than `laplacian` on all six (10.2 mm against 10.8; §13), and on the
# four faces at 512² 0.0121 against the two hybrid stages' 0.0150 (§13) — its unseen side less plausible than
# theirs (normals 10.6° off against 8.0°; `laplacian` 11.9°). splat: the
# statistical filter finds the shape, then 100 unfiltered steps at `none`'s own step size let the
# splats' images in: +1.1 dB held-out PSNR over `pca` for +0.3 points of geometry error (§14).
PIPELINES: dict[str, dict[str, Pipeline]] = {
    "register": {"default": Pipeline((Settings("pca", GAUSS_NEWTON_ITERATIONS, 0.0, optimizer="gauss-newton",
                                               noise=0.003, choose_levels=2, landmarks=False),
                                      Settings("hybrid", 200, 0.03, beta=1.0, lam=19.0)),
                                     "the closed-form coefficients, then 200 hybrid steps (docs/studies.md §9); "
                                     "laplacian where they cannot explain the scan (§23)",
                                     fallback=Fallback("laplacian", FALLBACK_RESIDUAL, FALLBACK_CODE))},
    "render": {"default": Pipeline((Settings("hybrid", 150, 0.05, beta=30.0, lam=19.0, mode_gain=1.0),
                                    Settings("hybrid", 300, 0.05, beta=10.0, lam=19.0, mode_gain=1.0),
                                    Settings("laplacian", 600, 0.01, lam=19.0)),
                                   "two hybrid stages, then the Laplacian filter (docs/studies.md §13)")},
    "splat": {"default": Pipeline((Settings("statistical", 300, 0.05, beta=1000.0, mode_gain=1.0),
                                   Settings("none", 100, 0.001)),
                                  "statistical for the shape, then a short unfiltered refinement")},
}


def resolve(method: str, preset: str = "tuned", job: str = "register", **overrides: Any) -> tuple[Settings, ...]:
    """The stages for ``method`` (a method or a pipeline of ``job``) under ``preset`` ('tuned' or
    'paper'), with ``overrides`` (non-None values) applied to every stage; for a pipeline,
    ``iterations`` is the total, split in proportion to the stages' own counts."""
    if preset not in ("tuned", "paper"):
        raise StatfitError(f"unknown preset {preset!r}; choose 'tuned' or 'paper'")
    if job not in JOBS:
        raise StatfitError(f"unknown job {job!r}; choose one of {', '.join(JOBS)}")
    load_plugins()
    pipelines = PIPELINES.get(job, {})
    offered = [*pipelines, *(name for name, m in METHODS.items() if job in m.tuned)]
    if method in pipelines:
        if preset == "paper":
            raise StatfitError(f"the {method!r} pipeline is ours, not the paper's; use --method statistical --preset paper")
        stages = pipelines[method].stages
    elif method in offered:
        if preset == "paper":
            if METHODS[method].paper is None or job not in PAPER_ITERATIONS:
                raise StatfitError(f"the paper has no {method!r} setting for {job}")
            stages = (replace(METHODS[method].paper, iterations=PAPER_ITERATIONS[job]),)
        else:
            stages = (METHODS[method].tuned[job],)
    else:
        raise StatfitError(f"unknown method {method!r} for {job}; choose one of {', '.join(offered)}")
    changes = {k: v for k, v in overrides.items() if v is not None}
    if "lr" in changes and any(s.optimizer == "gauss-newton" for s in stages):
        if len(stages) == 1:
            raise StatfitError(f"lr does not apply to the Gauss–Newton {method!r} stage (it has no step size); "
                               "--preset paper fits the coefficients with Adam")
        lr = changes.pop("lr")      # a pipeline's step size is its gradient stages'
        stages = tuple(s if s.optimizer == "gauss-newton" else replace(s, lr=lr) for s in stages)
    if len(stages) > 1 and "iterations" in changes:
        total = changes.pop("iterations")
        check_int("iterations", total, 1, MAX_ITERATIONS)
        stages = _split_iterations(stages, total)
    return tuple(replace(s, **changes) for s in stages)


def fallback(method: str, preset: str = "tuned", job: str = "register", **overrides: Any) -> Fallback | None:
    """The fallback of ``method``'s pipeline as shipped: None for a single method, the paper's
    preset, or any setting overridden (the fallback was measured against the tuned pipeline)."""
    load_plugins()
    pipeline = PIPELINES.get(job, {}).get(method)
    if pipeline is None or preset != "tuned" or any(v is not None for v in overrides.values()):
        return None
    return pipeline.fallback


def landmark_weight(method: str, job: str = "register") -> float:
    """The landmark term's weight of ``method`` (a method or a pipeline of ``job``); for a name
    neither offers, :data:`LANDMARK_WEIGHT`."""
    load_plugins()
    if method in PIPELINES.get(job, {}):
        return PIPELINES[job][method].landmark_weight
    return METHODS[method].landmark_weight if method in METHODS else LANDMARK_WEIGHT


def _split_iterations(stages: tuple[Settings, ...], total: int) -> tuple[Settings, ...]:
    """``stages`` with ``total`` iterations shared in proportion to their own counts (each ≥ 1)."""
    own = sum(s.iterations for s in stages)
    head = tuple(replace(s, iterations=max(1, round(s.iterations * total / own))) for s in stages[:-1])
    spent = sum(s.iterations for s in head)
    return head + (replace(stages[-1], iterations=max(1, total - spent)),)


# The methods whose stage takes B fits at once (``build`` with x0 (B, N, 3)): the filtered ones.
BATCHED_METHODS = ("statistical", "hybrid", "laplacian", "none")


def batchable(settings: Settings) -> bool:
    """Whether a stage of ``settings`` can step B fits of one model at once: a gradient stage of a
    filtered method whose Laplacian, if it has one, is the topology's alone (uniform)."""
    return (settings.optimizer != "gauss-newton" and settings.method in BATCHED_METHODS
            and (settings.method in ("statistical", "none") or settings.laplacian == "uniform"))


def build(settings: Settings, space: FitSpace, x0: torch.Tensor) -> tuple[Parametrization, Optimizer]:
    """Parametrisation and optimiser for one stage, starting from vertices ``x0`` (N, 3) (or (B, N, 3):
    B fits at once, for a :func:`batchable` stage)."""
    load_plugins()
    if settings.method not in METHODS:
        raise StatfitError(f"unknown method {settings.method!r}; choose one of {', '.join(METHODS)}")
    param, optimizer = METHODS[settings.method].build(settings, space, x0)
    if settings.settle and not isinstance(optimizer, UniformAdam):     # a plugin's method (Settings checks ours)
        raise StatfitError(f"settle brings UniformAdam's step size down; {settings.method!r} steps with "
                           f"{type(optimizer).__name__}")
    return param, optimizer

