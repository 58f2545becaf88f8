"""Study behind the ``statfit render`` defaults: every method on ICT normal maps of identity +
expression targets (expressions lie outside the identity model), at the paper's settings and at
candidate settings, plus the effect of the step size, the silhouette term and the alignment.

Each case: a model sample (seeded, σ = 1) plus one expression delta, rendered as a world-space
normal map (no antialiasing) from a frontal-oblique view. Every fit uses ``reconstruct`` with the
default rigid (pose + shape) alignment unless the configuration says otherwise. Metrics: mean
per-vertex error over all vertices, visible vertices (those of triangles seen in the target view)
and the rest, relative to the ground truth's RMS radius.

Results are appended to ``studies/results/render_align_shape_lr0.05.json`` after every fit (the
run resumes; ``study_render*.json``: §5's rows, from the alignment before session 9,
``--align-shape-lr 0.01``); ``--report`` prints the table in Markdown. Run from the repository root with
``../shared/data/ict-face`` present:

    PYTHONPATH=. python studies/study_render.py [--size 256] [--configs a,b] [--cases a,b] [--report]
    PYTHONPATH=. python studies/study_render.py --align-shape-lr 0.01 [--report]   # §5's start
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from statfit.structures.normal_map import NormalMap
from statfit.render.job import reconstruct
from statfit.core.settings import Settings
from statfit.geometry.metrics import visible_vertices
from statfit.model.statmodel import load_model
from statfit.synth.sample import camera_for_view, load_delta, sample_target
from statfit.renderer.images import render_target

sys.path.insert(0, str(Path(__file__).resolve().parent))
from study_register import Case  # noqa: E402  (an identity seed + an expression, seen from yaw/pitch)

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from common import ICT  # noqa: E402
RESULTS_DIR = ROOT / "studies" / "results"
# Rows per rigid-alignment step on the coefficients (``--align-shape-lr X``, shipped
# statfit.render.job.SHAPE_LR): study_render*.json for 0.01 (the start until session 9, §5),
# render_align_shape_lr<X>*.json otherwise (parallel runs: --results <that stem>_<part>.json).


CASES = (Case("jaw-open", 3, "jawOpen", 0.8, 20.0), Case("smile", 5, "mouthSmile_R", 1.0, -25.0),
         Case("brow-up", 7, "browInnerUp_L", 1.0, 30.0, 10.0), Case("puff", 11, "cheekPuff_L", 1.0, -15.0))


def S(method: str, iterations: int, lr: float, **kw) -> Settings:
    return Settings(method, iterations, lr, **kw)


# The render default until session 9: β 30 for 150 iterations, then β 10 for 300 (§11).
_TWO_HYBRID = (S("hybrid", 150, 0.05, beta=30.0, lam=19.0, mode_gain=1.0),
               S("hybrid", 300, 0.05, beta=10.0, lam=19.0, mode_gain=1.0))

# name → (method, preset, keyword arguments of reconstruct)
CONFIGS: dict[str, tuple[str, str, dict]] = {
    "paper/statistical": ("statistical", "paper", {}),
    "paper/laplacian": ("laplacian", "paper", {}),
    "paper/hybrid": ("hybrid", "paper", {}),
    "paper/regularized": ("regularized", "paper", {}),
    "paper/pca": ("pca", "paper", {}),
    "paper/none": ("none", "paper", {}),
    "paper/statistical lr 0.003": ("statistical", "paper", {"lr": 0.003}),
    "paper/statistical lr 0.03": ("statistical", "paper", {"lr": 0.03}),
    "paper/statistical no silhouette": ("statistical", "paper", {"silhouette_weight": 0.0}),
    "paper/statistical align none": ("statistical", "paper", {"align": "none"}),
    "paper/statistical silhouette 0.3": ("statistical", "paper", {"silhouette_weight": 0.3}),
    "paper/statistical silhouette 3": ("statistical", "paper", {"silhouette_weight": 3.0}),
    "paper/hybrid no silhouette": ("hybrid", "paper", {"silhouette_weight": 0.0}),
    "paper/hybrid align none": ("hybrid", "paper", {"align": "none"}),
    "statistical β1000 γ1 lr 0.01": ("", "", {"stages": (S("statistical", 3000, 0.01, beta=1000.0, mode_gain=1.0),)}),
    "statistical β1000 γ1 lr 0.003": ("", "", {"stages": (S("statistical", 3000, 0.003, beta=1000.0, mode_gain=1.0),)}),
    "statistical β1000 γ0.5 lr 0.005": ("", "", {"stages": (S("statistical", 3000, 0.005, beta=1000.0, mode_gain=0.5),)}),
    "statistical β30 γ1 lr 0.01": ("", "", {"stages": (S("statistical", 3000, 0.01, beta=30.0, mode_gain=1.0),)}),
    "two-stage β1000 γ1 → γ0.5": ("", "", {"stages": (S("statistical", 2000, 0.01, beta=1000.0, mode_gain=1.0),
                                                    S("statistical", 1000, 0.005, beta=1000.0, mode_gain=0.5))}),
    "pca lr 0.05": ("", "", {"stages": (S("pca", 3000, 0.05),)}),
    "pca lr 0.5": ("", "", {"stages": (S("pca", 3000, 0.5),)}),
    "laplacian lr 0.003": ("", "", {"stages": (S("laplacian", 3000, 0.003, lam=19.0),)}),
    "laplacian λ300 lr 0.01": ("", "", {"stages": (S("laplacian", 3000, 0.01, lam=300.0),)}),
    "hybrid β1000 lr 0.01": ("", "", {"stages": (S("hybrid", 3000, 0.01, beta=1000.0, lam=19.0),)}),
    "hybrid β30 γ1 lr 0.02": ("", "", {"stages": (S("hybrid", 3000, 0.02, beta=30.0, lam=19.0, mode_gain=1.0),)}),
    "hybrid β10 γ1 lr 0.01": ("", "", {"stages": (S("hybrid", 3000, 0.01, beta=10.0, lam=19.0, mode_gain=1.0),)}),
    "hybrid β30 λ50 γ1 lr 0.01": ("", "", {"stages": (S("hybrid", 3000, 0.01, beta=30.0, lam=50.0, mode_gain=1.0),)}),
    "hybrid β30 γ1 silhouette 3": ("", "", {"stages": (S("hybrid", 3000, 0.01, beta=30.0, lam=19.0, mode_gain=1.0),),
                                           "silhouette_weight": 3.0}),
    "hybrid β100 lr 0.01": ("", "", {"stages": (S("hybrid", 3000, 0.01, beta=100.0, lam=19.0),)}),
    "hybrid β30 lr 0.02": ("", "", {"stages": (S("hybrid", 3000, 0.02, beta=30.0, lam=19.0),)}),
    "hybrid β30 λ5 lr 0.01": ("", "", {"stages": (S("hybrid", 3000, 0.01, beta=30.0, lam=5.0),)}),
    "hybrid β30 γ1 lr 0.01": ("", "", {"stages": (S("hybrid", 3000, 0.01, beta=30.0, lam=19.0, mode_gain=1.0),)}),
    "statistical γ1 → hybrid β30": ("", "", {"stages": (S("statistical", 1500, 0.01, beta=1000.0, mode_gain=1.0),
                                                      S("hybrid", 1500, 0.01, beta=30.0, lam=19.0))}),
    "regularized β30 lr 0.003": ("", "", {"stages": (S("regularized", 3000, 0.003, beta=30.0),)}),
    "none lr 0.001": ("", "", {"stages": (S("none", 3000, 0.001),)}),
    "regularized β10 lr 0.01": ("", "", {"stages": (S("regularized", 3000, 0.01, beta=10.0),)}),
    "default": ("default", "tuned", {}),
    # The model's modes as built and without their rigid motion (docs/studies.md §45).
    "default (rigid modes kept)": ("default", "tuned", {"rigid_modes": "keep"}),
    "default (rigid modes dropped)": ("default", "tuned", {"rigid_modes": "drop"}),
    # Render schedules from the converged alignment start (--align-shape-lr 0.05; docs/studies.md §13).
    "two hybrid stages (the default until session 9)": ("", "", {"stages": _TWO_HYBRID}),
    "two hybrid stages → laplacian 300": ("", "", {"stages": (*_TWO_HYBRID, S("laplacian", 300, 0.01, lam=19.0))}),
    "two hybrid stages → laplacian 600 (the default since session 9)": ("", "", {"stages": (
        *_TWO_HYBRID, S("laplacian", 600, 0.01, lam=19.0))}),
}


def make_target(model, expressions: Path, case: Case, size: int):
    rng = np.random.default_rng(case.seed)
    gt = sample_target(model, rng, 1.0, load_delta(str(expressions), case.expression), case.weight)
    camera = camera_for_view(gt, case.yaw, case.pitch, size)
    normals, mask = render_target(gt, model.faces, camera)
    return gt, camera, NormalMap(normals, mask)


def errors(fit: np.ndarray, gt: np.ndarray, visible: np.ndarray) -> dict[str, float]:
    scale = float(np.sqrt(((gt - gt.mean(axis=0)) ** 2).sum(axis=1).mean()))
    err = np.linalg.norm(fit - gt, axis=1) / scale
    return {"all": float(err.mean()), "visible": float(err[visible].mean()), "hidden": float(err[~visible].mean())}


def load_results(path: Path) -> list[dict]:
    return json.loads(path.read_text()) if path.exists() else []


def report(results: list[dict]) -> str:
    cases = [c.name for c in CASES if any(r["case"] == c.name for r in results)]
    lines = ["| configuration | " + " | ".join(cases) + " | mean all | mean visible | mean hidden | s/fit |",
             "|---" * (len(cases) + 5) + "|"]
    for name in CONFIGS:
        rows = {r["case"]: r for r in results if r["config"] == name}
        if not rows:
            continue
        cells = [f"{rows[c]['all']:.4f}" if c in rows else "–" for c in cases]
        done = list(rows.values())
        mean = {k: np.mean([r[k] for r in done]) for k in ("all", "visible", "hidden", "seconds")}
        partial = "" if len(done) == len(cases) else f" ({len(done)} cases)"
        lines.append(f"| {name}{partial} | " + " | ".join(cells)
                     + f" | {mean['all']:.4f} | {mean['visible']:.4f} | {mean['hidden']:.4f} | {mean['seconds']:.0f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=256, help="the maps' size (and --report's rows)")
    parser.add_argument("--configs", default=",".join(CONFIGS))
    parser.add_argument("--cases", default=",".join(c.name for c in CASES))
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--report", action="store_true")
    parser.add_argument("--results", type=Path, help="Results file (default: the alignment step's own; parallel "
                        "runs write to separate files of its name; --report merges them).")
    parser.add_argument("--align-shape-lr", type=float, help="the rigid alignment's step on the coefficients "
                        "(default: the shipped SHAPE_LR); 0.01, the start until session 9, is §5's")
    args = parser.parse_args()
    if args.align_shape_lr is not None and not 0 < args.align_shape_lr < 10:   # also refuses NaN
        parser.error(f"--align-shape-lr must be a step between 0 and 10, got {args.align_shape_lr}")
    import statfit.render.job

    if args.align_shape_lr is not None:
        statfit.render.job.SHAPE_LR = args.align_shape_lr
    step = statfit.render.job.SHAPE_LR
    stem = "study_render" if step == 0.01 else f"render_align_shape_lr{step}"
    args.results = args.results or RESULTS_DIR / f"{stem}.json"
    if args.report:
        paths = sorted(RESULTS_DIR.glob(f"{stem}*.json"))
        print(report([r for path in paths for r in load_results(path) if r["size"] == args.size]))
        return
    torch.set_num_threads(args.threads)
    model = load_model(ICT / "ict_face_identity.npz")
    for case in (c for c in CASES if c.name in args.cases.split(",")):
        gt, camera, normal_map = make_target(model, ICT / "ict_face_expressions.npz", case, args.size)
        visible = visible_vertices(gt, model.faces, camera, normal_map.mask)
        template = errors(model.template, gt, visible)
        for name in args.configs.split(","):
            results = load_results(args.results)
            if any(r["case"] == case.name and r["config"] == name and r["size"] == args.size for r in results):
                continue
            method, preset, kwargs = CONFIGS[name]
            started = time.perf_counter()
            try:
                fit = reconstruct(model, normal_map, camera, method or "default", preset=preset or "tuned", **kwargs)
                row = errors(fit.vertices, gt, visible)
            except Exception as exc:  # a diverged configuration is a result too
                row = {"all": float("nan"), "visible": float("nan"), "hidden": float("nan"), "error": str(exc)}
            row |= {"case": case.name, "config": name, "size": args.size, "template": template["all"],
                    "seconds": time.perf_counter() - started}
            print(json.dumps(row), flush=True)
            args.results.parent.mkdir(exist_ok=True)
            args.results.write_text(json.dumps(load_results(args.results) + [row], indent=1))


if __name__ == "__main__":
    main()
