"""Registration study: picks the default pipeline of ``statfit register`` on the ICT face model.

Every method fits the ICT identity model's template to a partial scan (one view, 4300 points) of
a random identity plus an expression the identity model cannot represent. The study runs in four
phases, each pipeline on each case once (results are cached in the JSON, so an interrupted run
resumes where it stopped):

1. ``screen``     every method's grid on the three screening cases;
2. ``refine``     each method's best screened pipelines, plus a finer grid around them, on all six
                  test cases;
3. ``iterations`` the effect of the iteration count (500/1000/2000/4000) on the screening cases;
4. ``confirm``    each method at its best, the paper presets and the chosen default on the test
                  cases and on three held-out cases that played no part in any choice.

Usage (from the repository root, with ../shared/data/ict-face present)::

    PYTHONPATH=. python studies/study_register.py           # the full study; rewrites the doc
    PYTHONPATH=. python studies/study_register.py --quick   # a smoke test of a few minutes
    PYTHONPATH=. python studies/study_register.py --report  # only regenerate the doc

The full study writes studies/results/study_register.json and docs/study_register.md.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
from dataclasses import asdict, dataclass, replace
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from statfit.core.methods import METHODS
from statfit.core.settings import Settings
from statfit.geometry.metrics import evaluate, observed_vertices
from statfit.model.statmodel import StatModel, load_model
from statfit.registration.job import register
from statfit.synth.sample import load_delta, sample_target, scan_from_view

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from common import ICT_EXPRESSIONS as EXPRESSIONS_PATH, ICT_MODEL as MODEL_PATH  # noqa: E402
RESULTS_PATH = ROOT / "studies" / "results" / "study_register.json"
DOC_PATH = ROOT / "docs" / "study_register.md"
NUM_POINTS = 4300
REGIONS = ("all", "observed", "unobserved", "observed_surface")


@dataclass(frozen=True)
class Case:
    """One synthetic scan: an identity drawn with ``seed`` plus ``weight`` × an expression,
    seen from (``yaw``, ``pitch``) degrees."""

    name: str
    seed: int
    expression: str
    weight: float
    yaw: float
    pitch: float = 0.0


TEST_CASES = (
    Case("jaw-open", 3, "jawOpen", 1.0, 30),
    Case("smile", 11, "mouthSmile_R", 1.0, 0),
    Case("brow-up", 23, "browInnerUp_L", 0.9, -40),
    Case("cheek-puff", 37, "cheekPuff_L", 1.0, 30, 15),
    Case("mouth-left", 41, "mouthLeft", 0.8, 0, 15),
    Case("eye-blink", 53, "eyeBlink_L", 1.0, -40),
)
HELD_OUT_CASES = (
    Case("jaw-forward", 101, "jawForward", 1.0, 20),
    Case("frown", 103, "mouthFrown_R", 0.9, -30, 10),
    Case("nose-sneer", 107, "noseSneer_R", 1.0, 45),
)
SCREEN_CASES = tuple(c for c in TEST_CASES if c.name in ("jaw-open", "brow-up", "mouth-left"))
ALL_CASES = TEST_CASES + HELD_OUT_CASES


def stage(method: str, iterations: int, lr: float, **kwargs) -> Settings:
    """Shorthand for one ``Settings`` stage."""
    return Settings(method, iterations, lr, **kwargs)


def grid(method: str, iterations: int, lrs, **axes) -> list[tuple[Settings, ...]]:
    """Single-stage pipelines over the product of ``lrs`` and every keyword axis (lists)."""
    combos = [{}]
    for key, values in axes.items():
        combos = [dict(c, **{key: v}) for c in combos for v in values]
    return [(stage(method, iterations, lr, **c),) for lr in lrs for c in combos]


# Phase 1: the screening grid of each method family (its = iterations).
SCREEN_GRIDS: dict[str, list[tuple[Settings, ...]]] = {
    "pca": grid("pca", 1000, [0.01, 0.02, 0.03, 0.05, 0.1, 0.3, 1.0, 3.0]),
    "none": grid("none", 1000, [0.001, 0.003, 0.01]),
    "laplacian": (grid("laplacian", 1000, [0.003, 0.01, 0.03], lam=[5.0, 19.0, 100.0])
                  + grid("laplacian", 1000, [0.01, 0.03], lam=[300.0, 1000.0])
                  + grid("laplacian", 1000, [0.1], lam=[100.0, 300.0])),
    "regularized": (grid("regularized", 1000, [0.003, 0.01, 0.03], beta=[10.0, 100.0, 1000.0])
                    + grid("regularized", 1000, [0.1], beta=[30.0, 100.0, 300.0])
                    + grid("regularized", 1000, [0.3], beta=[10.0, 30.0])),
    "hybrid": grid("hybrid", 1000, [0.01, 0.03], beta=[30.0, 300.0], lam=[19.0, 100.0]),
    "statistical": (grid("statistical", 1000, [0.01, 0.03, 0.1], beta=[30.0, 100.0, 300.0, 1000.0],
                         mode_gain=[0.0, 0.5])
                    + grid("statistical", 1000, [0.01, 0.03], beta=[1000.0], mode_gain=[1.0, 2.0])),
    "staged": [
        (stage("pca", 300, 0.3), stage("statistical", 1000, 0.03, beta=300.0, mode_gain=0.5)),
        (stage("pca", 300, 0.3), stage("statistical", 1000, 0.01, beta=300.0)),
        (stage("statistical", 500, 0.03, beta=1000.0, mode_gain=0.5),
         stage("statistical", 1000, 0.03, beta=100.0, mode_gain=0.5)),
        (stage("statistical", 500, 0.03, beta=1000.0), stage("statistical", 1000, 0.01, beta=100.0)),
        (stage("statistical", 1000, 0.01, beta=1000.0, mode_gain=0.5),
         stage("statistical", 500, 0.01, beta=30.0, mode_gain=0.5)),
        (stage("statistical", 1000, 0.01, beta=1000.0, mode_gain=0.5),
         stage("statistical", 500, 0.003, beta=10.0, mode_gain=2.0)),
        (stage("statistical", 1000, 0.03, beta=1000.0, mode_gain=1.0),
         stage("statistical", 500, 0.01, beta=30.0, mode_gain=0.5)),
        (stage("statistical", 1000, 0.03, beta=1000.0, mode_gain=1.0),
         stage("statistical", 500, 0.01, beta=30.0, mode_gain=1.0)),
        (stage("pca", 1000, 0.03), stage("statistical", 500, 0.01, beta=30.0, mode_gain=0.5)),
    ],
}
# Phase 2: a finer grid around each family's best screened settings (added after the screen).
# The longer runs of pca and staged come from the iteration sweep, which showed both still improving.
REFINE_GRIDS: dict[str, list[tuple[Settings, ...]]] = {
    "statistical": [(stage("statistical", 1000, 0.03, beta=1000.0, mode_gain=1.5),),
                    (stage("statistical", 1000, 0.05, beta=1000.0, mode_gain=1.0),)],
    "pca": [(stage("pca", 4000, 0.05),), (stage("pca", 8000, 0.05),)],
    "staged": [(stage("statistical", 2667, 0.03, beta=1000.0, mode_gain=1.0),
                stage("statistical", 1333, 0.01, beta=30.0, mode_gain=0.5))],
}
REFINE_TOP = 3
# Phase 3: families whose best pipeline is re-run at these total iteration counts.
ITERATION_COUNTS = (500, 1000, 2000, 4000)
ITERATION_FAMILIES = ("statistical", "staged", "pca")
# The default is picked from these families (the ones built on the statistical filter).
DEFAULT_FAMILIES = ("statistical", "staged")
# The methods the default must beat.
BASELINES = ("pca", "laplacian", "hybrid", "regularized", "none")
# The outcome of the full study (its "default"), also what --quick runs.
RECOMMENDED: tuple[Settings, ...] = (
    Settings("statistical", 2667, 0.03, beta=1000.0, mode_gain=1.0),
    Settings("statistical", 1333, 0.01, beta=30.0, mode_gain=0.5),
)
# What the numbers say, written after reading them (docs/study_register.md quotes it).
FINDINGS: list[str] = [
    "- **The target is met on the six test cases but not on the held-out ones.** Test: default 0.190 cm "
    "all-vertex vs 0.205 for the best pca (8000 iterations), observed surface 0.045 vs 0.054. Held out: "
    "the default loses, 0.118 vs 0.098 all-vertex and 0.0314 vs 0.0307 observed surface.",
    "- The default's margin comes from the large expressions (jaw-open 0.462 vs 0.580, cheek-puff 0.201 "
    "vs 0.248). When the expression is small (close to the identity model: smile, brow-up, eye-blink, and "
    "all three held-out cases), a converged pca fit is better (brow-up 0.022 vs 0.059, eye-blink 0.026 vs "
    "0.056, frown 0.046 vs 0.070).",
    "- Nothing has converged at 500 iterations. Every family improves up to 4000, and pca still improves at "
    "8000 (jaw-open 0.647 at 4000 → 0.580 at 8000), so pca's 8000-iteration row is its best measured fit, "
    "not its limit. At an equal 1000-iteration budget the filter wins clearly: 0.254 (statistical) vs "
    "0.312 (pca) on the test cases.",
    "- mode_gain matters most. With γ = 1, statistical(1000 its, lr 0.03, β 1000) scores 0.320 on the "
    "screening cases, against 0.456 with γ = 0. γ = 2 is worse (0.413), and so is γ = 0.5 at that lr. "
    "Above β ≈ 300 the filter barely changes (β 300 and 1000 agree to 0.001).",
    "- Coarse to fine works. A second stage with β 30, γ 0.5 and lr 0.01 after the γ = 1, β 1000 stage "
    "lowers both errors: on the test cases, all-vertex 0.259 → 0.232 and observed surface 0.078 → 0.053, "
    "for 1500 iterations in total. Starting from a pca fit instead is worse: on the screening cases, "
    "pca(1000) > statistical 0.391 vs 0.295.",
    "- Laplacian, regularized and hybrid are never competitive once tuned: 0.412, 0.378 and 0.353 on the "
    "test cases against the default's 0.190. Laplacian's best lr (0.1) is at the edge of its grid, and "
    "none of the three was run past 1000 iterations.",
    "- Cost: the 4000-iteration default takes about 20 s on one loaded CPU thread (≈ 2.5× the "
    "1500-iteration version). The 1500-iteration version (1000 + 500) scores 0.232 / 0.053 on the test "
    "cases and 0.148 / 0.038 held out.",
    "- Paper presets (500 iterations): statistical beats regularized on all nine cases. It beats laplacian "
    "on all-vertex and unobserved error on 7 of 9 cases; it loses on jaw-open (1.045 vs 1.012 all, "
    "1.374 vs 1.326 unobserved) and jaw-forward (0.382 vs 0.354, 0.518 vs 0.499). Paper hybrid beats "
    "paper statistical on all nine cases, by 0.002–0.021 cm.",
]


def label(pipeline: tuple[Settings, ...]) -> str:
    """A short, unique, readable name of a pipeline, used as its key in the results."""
    return " > ".join(_stage_label(s) for s in pipeline)


def _stage_label(s: Settings) -> str:
    parts = [f"it={s.iterations}", f"lr={s.lr:g}"]
    if s.method in ("statistical", "hybrid", "regularized"):
        parts.append(f"beta={s.beta:g}")
    if s.power != 1.0:
        parts.append(f"power={s.power:g}")
    if s.method in ("laplacian", "hybrid"):
        parts.append(f"lam={s.lam:g}")
        if s.laplacian != "uniform":
            parts.append(s.laplacian)
    if s.mode_gain:
        parts.append(f"gain={s.mode_gain:g}")
    return f"{s.method}({', '.join(parts)})"


def as_python(pipeline: tuple[Settings, ...]) -> str:
    """The pipeline as a Python literal of ``Settings`` (only non-default fields)."""
    default = Settings("x", 1, 1.0)
    stages = []
    for s in pipeline:
        extra = [f"{k}={v!r}" for k, v in asdict(s).items()
                 if k not in ("method", "iterations", "lr") and v != getattr(default, k)]
        stages.append(f"Settings({', '.join([repr(s.method), str(s.iterations), repr(s.lr), *extra])})")
    return stages[0] if len(stages) == 1 else f"({', '.join(stages)})"


def with_iterations(pipeline: tuple[Settings, ...], total: int) -> tuple[Settings, ...]:
    """The pipeline with every stage's iterations scaled so they add up to ``total``."""
    scale = total / sum(s.iterations for s in pipeline)
    stages = [replace(s, iterations=max(1, round(s.iterations * scale))) for s in pipeline[:-1]]
    spent = sum(s.iterations for s in stages)
    return (*stages, replace(pipeline[-1], iterations=total - spent))


class Study:
    """The model, the cases, and the results store (a JSON file rewritten after every fit)."""

    def __init__(self, path: Path):
        torch.set_num_threads(1)
        self.path = path
        self.model: StatModel = load_model(str(MODEL_PATH))
        self.data = json.loads(path.read_text()) if path.exists() else {"cases": {}, "runs": {}, "phases": {}}

    def save(self) -> None:
        """Write the results atomically, so an interrupted run never leaves a broken file."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=self.path.parent, suffix=".tmp")
        with os.fdopen(fd, "w") as f:
            json.dump(self.data, f, indent=1, sort_keys=True)
        os.replace(tmp, self.path)

    @lru_cache(maxsize=None)
    def scan(self, case: Case) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ground truth (N, 3), scan points (M, 3) and observed-vertex mask (N,) of ``case``."""
        rng = np.random.default_rng(case.seed)
        delta = load_delta(str(EXPRESSIONS_PATH), case.expression)
        truth = sample_target(self.model, rng, sigma=1.0, delta=delta, delta_weight=case.weight)
        points = scan_from_view(truth, self.model.faces, rng, num_points=NUM_POINTS,
                                yaw_deg=case.yaw, pitch_deg=case.pitch)
        observed = observed_vertices(truth, points)
        if case.name not in self.data["cases"]:
            self.data["cases"][case.name] = asdict(case) | {
                "observed_fraction": float(observed.mean()),
                "template": self._errors(self.model.template, truth, observed)}
        return truth, points, observed

    def _errors(self, vertices: np.ndarray, truth: np.ndarray, observed: np.ndarray) -> dict[str, float]:
        report = evaluate(vertices, truth, self.model.faces, observed)
        return {region: report[region]["mean"] for region in REGIONS}

    def run(self, pipeline: tuple[Settings, ...], cases: tuple[Case, ...], phase: str) -> dict[str, dict]:
        """Fit ``pipeline`` on ``cases`` (skipping cached results); returns {case: errors + seconds}."""
        key = label(pipeline)
        entry = self.data["runs"].setdefault(key, {"stages": [asdict(s) for s in pipeline], "results": {}})
        phase_keys = self.data["phases"].setdefault(phase, [])
        if key not in phase_keys:
            phase_keys.append(key)
        for case in cases:
            if case.name in entry["results"]:
                continue
            truth, points, observed = self.scan(case)
            fit = register(self.model, points, stages=pipeline)
            entry["results"][case.name] = self._errors(fit.vertices, truth, observed) | {"seconds": fit.seconds}
            self.save()
            print(f"  {case.name:12s} all {entry['results'][case.name]['all']:.4f}  {key}", flush=True)
        return {c.name: entry["results"][c.name] for c in cases}

    def mean(self, key: str, cases: tuple[Case, ...], region: str = "all") -> float:
        """Mean of ``region``'s error of run ``key`` over ``cases`` (NaN if any is missing)."""
        results = self.data["runs"].get(key, {}).get("results", {})
        if any(c.name not in results for c in cases):
            return math.nan
        return float(np.mean([results[c.name][region] for c in cases]))

    def ranked(self, keys: list[str], cases: tuple[Case, ...]) -> list[str]:
        """``keys`` with results on all ``cases``, best (lowest mean all-vertex error) first."""
        keys = [k for k in keys if not math.isnan(self.mean(k, cases))]
        return sorted(keys, key=lambda k: self.mean(k, cases))

    def pipeline(self, key: str) -> tuple[Settings, ...]:
        """The pipeline stored under ``key``."""
        return tuple(Settings(**(s | {"betas": tuple(s["betas"])})) for s in self.data["runs"][key]["stages"])


def family(pipeline: tuple[Settings, ...]) -> str:
    """The method family of a pipeline: its method, or 'staged' for a multi-stage pipeline."""
    return pipeline[0].method if len(pipeline) == 1 else "staged"


def paper_pipelines() -> dict[str, tuple[Settings, ...]]:
    """The paper-faithful single-stage pipeline of every method."""
    return {name: (method.paper,) for name, method in METHODS.items() if method.paper is not None}


def run_study(study: Study) -> None:
    """All four phases; records each family's best, the default and the sweeps in ``study.data``."""
    print("phase 1: screen", flush=True)
    for pipelines in SCREEN_GRIDS.values():
        for p in pipelines:
            study.run(p, SCREEN_CASES, "screen")

    print("phase 2: refine", flush=True)
    for name, pipelines in SCREEN_GRIDS.items():
        top = study.ranked([label(p) for p in pipelines], SCREEN_CASES)[:REFINE_TOP]
        for p in [study.pipeline(k) for k in top] + REFINE_GRIDS.get(name, []):
            study.run(p, TEST_CASES, "refine")
    refined = study.data["phases"]["refine"]
    best = {name: study.ranked([k for k in refined if family(study.pipeline(k)) == name], TEST_CASES)[0]
            for name in SCREEN_GRIDS}
    default = choose_default(study, best)

    print("phase 3: iterations", flush=True)
    sweeps = {}
    for name in ITERATION_FAMILIES:
        runs = [with_iterations(study.pipeline(best[name]), n) for n in ITERATION_COUNTS]
        sweeps[name] = [label(p) for p in runs]
        for p in runs:
            study.run(p, SCREEN_CASES, "iterations")

    print("phase 4: confirm", flush=True)
    paper = paper_pipelines()
    for p in [study.pipeline(k) for k in best.values()] + list(paper.values()):
        study.run(p, ALL_CASES, "confirm")
    study.data["selection"] = {"best": best, "default": default, "iterations": sweeps,
                               "paper": {m: label(p) for m, p in paper.items()}}
    study.save()
    if default != label(RECOMMENDED):
        print(f"note: the study now picks {default}, not RECOMMENDED = {label(RECOMMENDED)}")


def choose_default(study: Study, best: dict[str, str]) -> str:
    """The refined pipeline of a DEFAULT_FAMILIES family with the lowest mean all-vertex error on
    the test cases among those whose observed-region surface distance is below the best pca's."""
    pca_surface = study.mean(best["pca"], TEST_CASES, "observed_surface")
    keys = [k for k in study.data["phases"]["refine"] if family(study.pipeline(k)) in DEFAULT_FAMILIES]
    passing = [k for k in study.ranked(keys, TEST_CASES) if study.mean(k, TEST_CASES, "observed_surface") < pca_surface]
    return (passing or study.ranked(keys, TEST_CASES))[0]


def fmt(value: float, digits: int = 3) -> str:
    return "–" if math.isnan(value) else f"{value:.{digits}f}"


def results_table(study: Study, rows: list[tuple[str, str]], cases: tuple[Case, ...]) -> list[str]:
    """Markdown table of mean errors (cm) and seconds over ``cases`` for (row name, run key) rows."""
    lines = ["| | pipeline | all | observed | unobserved | observed surface | seconds |",
             "|---|---|---|---|---|---|---|"]
    for name, key in rows:
        values = [fmt(study.mean(key, cases, r)) for r in REGIONS] + [fmt(study.mean(key, cases, "seconds"), 1)]
        lines.append(f"| {name} | `{key}` | " + " | ".join(values) + " |")
    return lines


def grid_axes(pipelines: list[tuple[Settings, ...]]) -> str:
    """The swept values of a single-stage grid, e.g. 'lr ∈ {0.01, 0.03}, beta ∈ {30, 300}'."""
    if any(len(p) > 1 for p in pipelines):
        return f"{len(pipelines)} hand-picked pipelines (below)"
    axes = []
    for key in ("iterations", "lr", "beta", "lam", "laplacian", "mode_gain"):
        values = sorted({getattr(p[0], key) for p in pipelines}, key=str)
        if len(values) > 1 or key in ("iterations", "lr"):
            axes.append(f"{key} ∈ {{{', '.join(f'{v:g}' if isinstance(v, float) else str(v) for v in values)}}}")
    return ", ".join(axes)


def case_table(study: Study) -> list[str]:
    lines = ["| case | set | seed | expression (weight) | yaw, pitch | observed vertices | template error (all / observed surface) |",
             "|---|---|---|---|---|---|---|"]
    for case in ALL_CASES:
        info = study.data["cases"][case.name]
        kind = "held out" if case in HELD_OUT_CASES else ("test, screen" if case in SCREEN_CASES else "test")
        lines.append(f"| {case.name} | {kind} | {case.seed} | {case.expression} ({case.weight:g}) | "
                     f"{case.yaw:g}°, {case.pitch:g}° | {100 * info['observed_fraction']:.0f}% | "
                     f"{info['template']['all']:.3f} / {info['template']['observed_surface']:.3f} |")
    return lines


def per_case_table(study: Study, rows: list[tuple[str, str]], region: str) -> list[str]:
    """One column per case: ``region``'s mean error of each (name, key) row."""
    lines = ["| | " + " | ".join(c.name for c in ALL_CASES) + " |", "|---|" + "---|" * len(ALL_CASES)]
    for name, key in rows:
        results = study.data["runs"][key]["results"]
        lines.append(f"| {name} | " + " | ".join(fmt(results[c.name][region]) if c.name in results else "–"
                                                 for c in ALL_CASES) + " |")
    return lines


def target_check(study: Study, default: str, best: dict[str, str], cases: tuple[Case, ...]) -> list[str]:
    """Lines saying whether the default beats every tuned baseline (all) and pca (observed surface)."""
    mine = study.mean(default, cases)
    rivals = {name: key for name, key in best.items() if key != default}
    beaten = [name for name, key in rivals.items() if study.mean(key, cases) <= mine]
    surface, pca_surface = (study.mean(default, cases, "observed_surface"),
                            study.mean(best["pca"], cases, "observed_surface"))
    return [f"- lowest mean all-vertex error: **{'yes' if not beaten else 'no'}** ({mine:.4f} cm; best other "
            f"{min(study.mean(k, cases) for k in rivals.values()):.4f}"
            + (f"; beaten or equalled by {', '.join(beaten)}" if beaten else "") + ")",
            f"- observed-surface distance below the best pca's: **{'yes' if surface < pca_surface else 'no'}** "
            f"({surface:.4f} vs {pca_surface:.4f} cm)"]


def losses(study: Study, default: str, best: dict[str, str]) -> list[str]:
    """Every case where a tuned baseline has a lower all-vertex error than the default, or the best
    pca a lower observed-surface distance."""
    lines = []
    mine = study.data["runs"][default]["results"]
    for name in BASELINES:
        theirs = study.data["runs"][best[name]]["results"]
        regions = ("all", "observed_surface") if name == "pca" else ("all",)
        for case in ALL_CASES:
            for region in regions:
                if theirs[case.name][region] < mine[case.name][region]:
                    lines.append(f"- {case.name}: best {name} has the lower {region.replace('_', ' ')} error, "
                                 f"{theirs[case.name][region]:.3f} vs {mine[case.name][region]:.3f} cm")
    return lines or ["- none"]


def write_report(study: Study, path: Path = DOC_PATH) -> None:
    """Regenerate the study's markdown document from the results."""
    sel = study.data["selection"]
    best, default, paper = sel["best"], sel["default"], sel["paper"]
    final_rows = ([("**default**", default)] + [(f"best {name}", key) for name, key in best.items()]
                  + [(f"paper {name}", key) for name, key in paper.items()])
    out = ["# Registration study: choosing `statfit register`'s default", "",
           "Generated by `studies/study_register.py` from `studies/results/study_register.json`; "
           "do not edit by hand.", "",
           "The ICT face identity model (11,248 vertices, 100 modes, cm) is fitted to partial scans "
           f"({NUM_POINTS} points, one view, orthographic ray casting) of a random identity (coefficients "
           "~ N(0, 1)) plus one ICT expression, which lies outside the identity model. Errors are means "
           "in cm: per-vertex distance to the ground truth over all / observed / unobserved vertices, "
           "and the distance of the observed ground-truth vertices to the fitted surface. Seconds are "
           "wall time of one fit on one CPU thread (a shared 2-core machine: expect ±20%).", "",
           "## Cases", "", *case_table(study), "",
           "Screening used the three `test, screen` cases; refinement and the choice of the default used "
           "the six test cases; the three held-out cases were only used to confirm.", "",
           "## Recommended default", "", "```python", as_python(study.pipeline(default)), "```", "",
           "## Final table: six test cases", "", *results_table(study, final_rows, TEST_CASES), "",
           "## Final table: three held-out cases", "", *results_table(study, final_rows, HELD_OUT_CASES), "",
           "## Target", "", "On the test cases:", *target_check(study, default, best, TEST_CASES), "",
           "On the held-out cases:", *target_check(study, default, best, HELD_OUT_CASES), "",
           "Cases where a tuned baseline beats the default (all-vertex error; observed surface for pca):", "", *losses(study, default, best), "",
           "## Findings", "", *FINDINGS, "",
           "## Paper presets, per case", "",
           "All-vertex error:", "", *per_case_table(study, [(f"paper {m}", k) for m, k in paper.items()], "all"), "",
           "Unobserved-vertex error:", "",
           *per_case_table(study, [(f"paper {m}", k) for m, k in paper.items()], "unobserved"), "",
           "## Iterations", "",
           "Each family's best pipeline with its iterations scaled to a total of "
           f"{', '.join(map(str, ITERATION_COUNTS))}, on the screening cases.", ""]
    for name, keys in sel["iterations"].items():
        out += [f"**{name}**", "", *results_table(study, [(f"{_total(study, k)} its", k) for k in keys],
                                                  SCREEN_CASES), ""]
    out += ["## Sweeps", "",
            "Screened on the screening cases (mean errors below); the top "
            f"{REFINE_TOP} of each family, plus a finer grid around them, were re-run on all six test cases.", ""]
    for name, pipelines in SCREEN_GRIDS.items():
        screened = study.ranked([label(p) for p in pipelines], SCREEN_CASES)
        refined = study.ranked([k for k in study.data["phases"]["refine"] if family(study.pipeline(k)) == name],
                               TEST_CASES)
        out += [f"### {name}", "", f"Screening grid: {grid_axes(pipelines)}.", "",
                f"Best: `{as_python(study.pipeline(best[name]))}`", "",
                "Refined (six test cases):", "", *results_table(study, [(str(i + 1), k) for i, k in enumerate(refined)],
                                                                TEST_CASES), "",
                "Screened (three screening cases):", "",
                *results_table(study, [(str(i + 1), k) for i, k in enumerate(screened)], SCREEN_CASES), ""]
    path.write_text("\n".join(out))


def _total(study: Study, key: str) -> int:
    return sum(s.iterations for s in study.pipeline(key))


def quick(path: Path) -> None:
    """A few-minute smoke test: the paper presets and the recommended default on one case."""
    study = Study(path)
    case = (TEST_CASES[0],)
    for p in [*(paper_pipelines()[m] for m in ("statistical", "laplacian", "regularized", "pca")), RECOMMENDED]:
        study.run(p, case, "quick")
    print("\n".join(results_table(study, [(str(i + 1), k) for i, k in enumerate(study.data["phases"]["quick"])],
                                  case)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help="smoke test on one case (results in a temp file)")
    mode.add_argument("--report", action="store_true", help="only regenerate the doc from the results")
    parser.add_argument("--out", type=Path, help="results JSON (default: the committed results, or a temp file with --quick)")
    args = parser.parse_args()
    if args.quick:
        quick(args.out or Path(tempfile.gettempdir()) / "study_register_quick.json")
        return
    study = Study(args.out or RESULTS_PATH)
    if not args.report:
        run_study(study)
    write_report(study)


if __name__ == "__main__":
    main()
