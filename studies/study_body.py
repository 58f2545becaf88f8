"""Full bodies from one normal map (issue 14's study, the paper's body figure as numbers).

Model: ``statfit model build-makehuman`` (300 modes, 5,000 bodies, seed 0), built once into a
cache outside the repository. Targets: held-out MakeHuman bodies (``statfit synth body``: asymmetric,
with the asym and expression targets and sliders in the tails, none of which the model saw),
seeds 1..6, each seen from two views (yaw 30° and −60°, pitch 10°). Every method at its tuned
render setting (``resolve(method, job="render")``), default rigid alignment (its step on the
coefficients: ``--align-shape-lr``, shipped ``statfit.render.job.SHAPE_LR``).

Metrics, per fit, in mm: mean vertex error over all vertices, the vertices seen in the map and the
rest ("unseen"): raw; "scaled", after the one thing a normal map cannot tell — the body's size at
its distance (normals do not change when the scene is scaled about the camera centre): the fit
scaled about the camera centre by the closed-form least-squares factor; and "aligned" (the
ranking measure), after the least-squares similarity (Umeyama), which also takes out the few
degrees of whole-body rotation that one view leaves loose. Plausibility of the unseen
side: RMS distance of its vertices to the model's span (the ground truth's own is reported beside
it: held-out bodies are not in the span either) and the mean angle between fitted and true normals
of the unseen triangles.

Results are appended after every fit (a rerun resumes) to ``studies/results/study_body_align_shape_lr<X>.json``
for the alignment's step X on the coefficients, or ``study_body.json`` for the pose's step 0.01 (the
shipped start until session 9; ``study_body_plain_normals.json``: the fits before the normal term
was antialiased). Rows named ``default`` are the render default since session 9; the default before
it is ``candidate:two-hybrid-stages``;
``--report`` prints the Markdown tables of docs/studies.md; ``--trace SEED,YAW`` follows one fit's
error per region (on ``--threads``, 2 unless told; the study's fits run on 1). From the repository root:

    PYTHONPATH=. python studies/study_body.py [--size 384] [--methods a,b] [--workers 2] [--report]
    PYTHONPATH=. python studies/study_body.py --trace 1,-60 --methods default [--threads 1]
    PYTHONPATH=. python studies/study_body.py --trace 2,-60 --methods candidate:pca500p-default
    PYTHONPATH=. python studies/study_body.py --align-shape-lr 0.01 [--report]   # the start until session 9 (§13)
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from functools import lru_cache, partial
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from common import MAKEHUMAN  # noqa: E402

RESULTS_DIR = ROOT / "studies" / "results"
# The rows of the rigid alignment's step on the coefficients 0.01 (the shipped start until session 9).
POSE_STEP_RESULTS = RESULTS_DIR / "study_body.json"
MODEL_CACHE = Path(os.environ.get("STATFIT_BODY_MODEL", "/tmp/statfit-study-body-300.npz"))
SEEDS = (1, 2, 3, 4, 5, 6)
VIEWS = ((30.0, 10.0), (-60.0, 10.0))
METHODS = ("default", "hybrid", "statistical", "laplacian", "pca", "regularized", "none")
# Candidate render schedules for bodies (``--candidates``), reported apart from the methods.
_HYBRID = {"lam": 19.0, "mode_gain": 1.0}
_B30 = ("hybrid", 150, 0.05, {"beta": 30.0, **_HYBRID})     # the two hybrid stages of the render
_B10 = ("hybrid", 300, 0.05, {"beta": 10.0, **_HYBRID})     # default until session 9
_B3 = ("hybrid", 300, 0.05, {"beta": 3.0, **_HYBRID})


def _laplacian(iterations: int, lr: float = 0.01) -> tuple:
    return ("laplacian", iterations, lr, {"lam": 19.0})


CANDIDATES = {
    "hybrid-b30-900": (("hybrid", 900, 0.05, {"beta": 30.0, **_HYBRID}),),
    "stat300-hybrid600": (("statistical", 300, 0.05, {"beta": 1000.0, "mode_gain": 1.0}),
                          ("hybrid", 600, 0.05, {"beta": 30.0, **_HYBRID})),
    "hybrid-b300-300-b30-600": (("hybrid", 300, 0.05, {"beta": 300.0, **_HYBRID}),
                                ("hybrid", 600, 0.05, {"beta": 30.0, **_HYBRID})),
    "stat1500-hybrid1500": (("statistical", 1500, 0.01, {"beta": 1000.0, "mode_gain": 1.0}),
                            ("hybrid", 1500, 0.01, {"beta": 30.0, **_HYBRID})),
    # The render default until session 9: two hybrid stages (its rows in the results files).
    "two-hybrid-stages": (_B30, _B10),
    # The span first, each coefficient at its own Adam step (as `pca`, which wins two side views),
    # then the render default's two hybrid stages.
    "pca500-default": (("pca", 500, 0.05, {}), _B30, _B10),
    # ... with a Gaussian prior on the coefficients (0.1 · mean(c²)): body 4's side view diverged without.
    # Shipped as the opt-in `render --method span-first` in sessions 7–8 (docs/studies.md §13).
    "pca500p-default": (("pca", 500, 0.05, {"prior": 0.1}), _B30, _B10),
    # ... shorter (550 iterations, against the default's 450; faces' ≤ 30 s at 512²).
    "pca250p-h100-h200": (("pca", 250, 0.05, {"prior": 0.1}), ("hybrid", 100, 0.05, {"beta": 30.0, **_HYBRID}),
                          ("hybrid", 200, 0.05, {"beta": 10.0, **_HYBRID})),
    # From the converged alignment start (``--align-shape-lr 0.05``, §13), where `laplacian` fits
    # closest: the default's stages with more freedom off the span in the second (β 3, β 1).
    "h30-150-b3-300": (_B30, _B3),
    "h30-150-b1-300": (_B30, ("hybrid", 300, 0.05, {"beta": 1.0, **_HYBRID})),
    # ... then a smaller step to settle (UniformAdam at 0.05 ends where its step lets it).
    "h30-150-b3-300-b3s-300": (_B30, _B3, ("hybrid", 300, 0.01, {"beta": 3.0, **_HYBRID})),
    "h30-150-b3-300-b0.3-300": (_B30, _B3, ("hybrid", 300, 0.01, {"beta": 0.3, **_HYBRID})),
    # ... or the Laplacian filter last (what it fits closer than any span), after β 3, after β 30 alone,
    # or after the two hybrid stages (600 iterations at lr 0.01 after them: the render default since
    # session 9, whose rows are `default` in study_body_align_shape_lr0.05.json).
    "h30-150-b3-300-lap-300": (_B30, _B3, _laplacian(300)),
    "h30-150-b3-300-lap-600": (_B30, _B3, _laplacian(600)),
    "h30-150-b3-300-lap-300-laps-300": (_B30, _B3, _laplacian(300), _laplacian(300, 0.003)),
    "h30-150-lap-600": (_B30, _laplacian(600)),
    "two-hybrid-lap-300": (_B30, _B10, _laplacian(300)),
    "two-hybrid-lap-300-laps-300": (_B30, _B10, _laplacian(300), _laplacian(300, 0.003)),
}


def schedule(method: str) -> dict:
    """``reconstruct``'s keyword for a method name of the study: a candidate ("candidate:NAME") runs
    its stages; a method, its own."""
    return {"stages": candidate_stages(method.split(":", 1)[1])} if method.startswith("candidate:") else {}


def candidate_stages(name: str):
    """The ``Settings`` stages of a candidate schedule."""
    from statfit.core.settings import Settings

    return tuple(Settings(method, iterations, lr, **extra) for method, iterations, lr, extra in CANDIDATES[name])


@lru_cache(maxsize=1)
def body_space():
    """The MakeHuman targets, read once per process (~8 s)."""
    from statfit.model.importers.makehuman import read_makehuman
    from statfit.model.importers.makehuman_shapes import BodySpace

    return BodySpace(read_makehuman(MAKEHUMAN))


@lru_cache(maxsize=1)
def body_model():
    """The study's model (built into ``MODEL_CACHE`` the first time, ~25 s), loaded once per process."""
    from statfit.model.importers.makehuman_shapes import body_regions, build_body_model
    from statfit.model.statmodel import load_model, save_model

    if not MODEL_CACHE.exists():
        space = body_space()
        save_model(build_body_model(space, 300, 5000, 0, body_regions(space)).model, MODEL_CACHE, np.float32)
    return load_model(MODEL_CACHE)


def held_out_body(seed: int) -> np.ndarray:
    """Held-out body ``seed`` (N, 3), m; kept beside ``MODEL_CACHE`` after its first making (the
    targets' reading, ~10 s, is then paid once, not by every worker process)."""
    path = MODEL_CACHE.with_name(f"{MODEL_CACHE.stem}-held-out-{seed}.npy")
    if path.exists():
        return np.load(path)
    space = body_space()
    body = space.shapes(space.weights(np.random.default_rng(seed), 1, "held_out"))[0]
    partial = path.with_name(f"{path.stem}.{os.getpid()}.npy")      # workers may make it at once: whole files only
    np.save(partial, body)
    os.replace(partial, path)
    return body


def view(seed: int, yaw: float, pitch: float, size: int):
    """(model, held-out body (N, 3), camera, its NormalMap) of one study case."""
    from statfit.structures.normal_map import NormalMap
    from statfit.synth.sample import camera_for_view
    from statfit.renderer.images import render_target

    model = body_model()
    gt = held_out_body(seed)
    camera = camera_for_view(gt, yaw, pitch, size)
    return model, gt, camera, NormalMap(*render_target(gt, model.faces, camera))


def scale_about(fit: np.ndarray, gt: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """``fit`` scaled about ``centre`` by the least-squares factor that brings it to ``gt``."""
    a, b = fit - centre, gt - centre
    return centre + (a * b).sum() / (a * a).sum() * a


def off_span(model, vertices: np.ndarray, where: np.ndarray) -> float:
    """RMS distance (m) of ``where``'s vertices from the model's span: the residual of the shape
    after its projection onto the modes, over those vertices."""
    delta = (vertices - model.template).reshape(-1)
    residual = (delta - model.basis @ (model.basis.T @ delta)).reshape(-1, 3)
    return float(np.sqrt((residual[where] ** 2).sum(axis=1).mean()))


def normal_angle(fit: np.ndarray, gt: np.ndarray, faces: np.ndarray, where: np.ndarray) -> float:
    """Mean angle (degrees) between the fitted and true normals of triangles with all vertices in ``where``."""
    def normals(v):
        n = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
        return n / np.linalg.norm(n, axis=1, keepdims=True).clip(1e-30)
    inside = where[faces].all(axis=1)
    cosine = (normals(fit)[inside] * normals(gt)[inside]).sum(axis=1).clip(-1, 1)
    return float(np.degrees(np.arccos(cosine)).mean())


def run_case(task: tuple[int, float, float, str, int], iterations: int | None = None,
             align_shape_lr: float | None = None, also_at: tuple[int, ...] = (), rigid_modes: str = "auto") -> dict:
    """One fit of a held-out body from one view; ``iterations`` other than the method's (tests);
    ``align_shape_lr`` the rigid alignment's step on the coefficients (None: as shipped);
    ``also_at``: iteration counts (multiples of 10) whose rows come too, under "at", from the
    fit's own snapshots: the row a shorter fit of a method with a constant step would give;
    ``rigid_modes``: the model's modes with or without their rigid motion (``reconstruct``'s)."""
    seed, yaw, pitch, method, size = task
    import torch

    torch.set_num_threads(1)
    import statfit.render.job
    from statfit.geometry.metrics import visible_vertices
    from statfit.render.job import reconstruct

    if align_shape_lr is not None:
        statfit.render.job.SHAPE_LR = align_shape_lr

    model, gt, camera, normal_map = view(seed, yaw, pitch, size)
    snapshots: dict[int, np.ndarray] = {}

    def keep(iteration: int, vertices: np.ndarray) -> None:
        if iteration in also_at:
            snapshots[iteration] = vertices.copy()

    started = time.perf_counter()
    overrides = {} if iterations is None else {"iterations": iterations}
    fit = reconstruct(model, normal_map, camera, method, threads=1, on_snapshot=keep if also_at else None,
                      rigid_modes=rigid_modes, **(overrides | schedule(method))).vertices
    seconds = time.perf_counter() - started
    seen = visible_vertices(gt, model.faces, camera)
    row = {"seed": seed, "yaw": yaw, "pitch": pitch, "method": method, "size": size, "seconds": seconds,
           "seen_share": float(seen.mean()), **_errors(model, fit, gt, camera, seen)}
    if also_at:
        row["at"] = {it: _errors(model, snapshots[it], gt, camera, seen) for it in also_at}
    return row


def _errors(model, fit: np.ndarray, gt: np.ndarray, camera, seen: np.ndarray) -> dict:
    """The row's errors of ``fit`` (N, 3) against ``gt``: raw, scaled and aligned (mm; all, seen
    and unseen vertices), the unseen side's distance from the span and its normals' angle."""
    from statfit.geometry.align import umeyama

    centre = -camera.rotation.numpy().T @ camera.world_to_camera[:3, 3].numpy()
    scaled = scale_about(fit, gt, centre)
    aligned = umeyama(fit, gt, with_scale=True).apply(fit)
    row = {}
    for name, shape in (("raw", fit), ("scaled", scaled), ("aligned", aligned)):
        error = np.linalg.norm(shape - gt, axis=1) * 1000
        row[name] = {"all": float(error.mean()), "seen": float(error[seen].mean()),
                     "unseen": float(error[~seen].mean())}
    row["off_span_unseen_mm"] = off_span(model, fit, ~seen) * 1000
    row["gt_off_span_unseen_mm"] = off_span(model, gt, ~seen) * 1000
    row["normal_angle_unseen_deg"] = normal_angle(aligned, gt, model.faces, ~seen)
    return row


def trace(seed: int, yaw: float, method: str = "default", size: int = 384, every: int = 50, threads: int = 2) -> None:
    """Print the aligned error (mm) over all, seen and unseen vertices and per region every
    ``every`` iterations of one fit (iteration 0: after the rigid alignment, which also fits the
    model's coefficients): where along the fit a view's error is made."""
    import torch

    torch.set_num_threads(threads)
    from statfit.geometry.align import umeyama
    from statfit.render.job import reconstruct
    from statfit.geometry.metrics import visible_vertices

    model, gt, camera, normal_map = view(seed, yaw, VIEWS[0][1], size)
    seen = visible_vertices(gt, model.faces, camera)
    regions = {name: model.regions[name] for name in ("head", "torso", "arms", "legs") if name in model.regions}

    def aligned_error(vertices: np.ndarray) -> np.ndarray:       # (N,) mm after the similarity to the truth
        return np.linalg.norm(umeyama(vertices, gt, with_scale=True).apply(vertices) - gt, axis=1) * 1000

    def report_at(iteration: int, vertices: np.ndarray) -> None:
        if iteration % every:
            return
        error = aligned_error(vertices)
        parts = " ".join(f"{name} {error[where].mean():.1f}" for name, where in regions.items())
        print(f"iteration {iteration:5d}: all {error.mean():.1f} seen {error[seen].mean():.1f} "
              f"unseen {error[~seen].mean():.1f} | {parts}", flush=True)

    fit = reconstruct(model, normal_map, camera, method, threads=threads, on_snapshot=report_at, **schedule(method))
    print(f"final: all {aligned_error(fit.vertices).mean():.1f} mm after {fit.iterations} iterations")


def results_file(align_shape_lr: float | None = None) -> Path:
    """Where the rows of the rigid alignment's step ``align_shape_lr`` (None: the shipped one) go."""
    from statfit.render.job import SHAPE_LR

    step = SHAPE_LR if align_shape_lr is None else align_shape_lr
    return POSE_STEP_RESULTS if step == 0.01 else RESULTS_DIR / f"study_body_align_shape_lr{step}.json"


def done_rows(results: Path | None = None) -> list[dict]:
    results = results_file() if results is None else results
    return [json.loads(line) for line in results.read_text().splitlines()] if results.exists() else []


def report(rows: list[dict]) -> str:
    methods = [m for m in METHODS if any(r["method"] == m for r in rows)]
    methods += sorted({r["method"] for r in rows if r["method"].startswith("candidate:")})
    cases = sorted({(r["seed"], r["yaw"]) for r in rows})
    lines = ["| method | fits | all (raw) | all (scaled) | all | seen | unseen | unseen off-span | unseen normal ° | s per fit |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for method in methods:
        mine = [r for r in rows if r["method"] == method]
        mean = lambda f: np.mean([f(r) for r in mine])  # noqa: E731
        lines.append(f"| {method} | {len(mine)} | {mean(lambda r: r['raw']['all']):.1f} | {mean(lambda r: r['scaled']['all']):.1f} | "
                     f"{mean(lambda r: r['aligned']['all']):.1f} | "
                     f"{mean(lambda r: r['aligned']['seen']):.1f} | {mean(lambda r: r['aligned']['unseen']):.1f} | "
                     f"{mean(lambda r: r['off_span_unseen_mm']):.2f} | {mean(lambda r: r['normal_angle_unseen_deg']):.1f} | "
                     f"{mean(lambda r: r['seconds']):.0f} |")
    gt_span = np.mean([r["gt_off_span_unseen_mm"] for r in rows])
    lines.append(f"\nGround truth's own unseen off-span distance: {gt_span:.2f} mm (mean over cases).\n")
    lines.append("| body, view | " + " | ".join(methods) + " | best |")
    lines.append("|---|" + "---|" * (len(methods) + 1))
    for seed, yaw in cases:
        errors = {m: next((r["aligned"]["all"] for r in rows if (r["seed"], r["yaw"], r["method"]) == (seed, yaw, m)),
                          np.nan) for m in methods}
        unseen = {m: next((r["aligned"]["unseen"] for r in rows if (r["seed"], r["yaw"], r["method"]) == (seed, yaw, m)),
                          np.nan) for m in methods}
        best = min(errors, key=lambda m: errors[m] if np.isfinite(errors[m]) else np.inf)
        lines.append(f"| {seed}, yaw {yaw:.0f} | " + " | ".join(f"{errors[m]:.1f} ({unseen[m]:.1f})" for m in methods)
                     + f" | {best} |")
    lines.append("\nPer body, both views averaged: aligned all-vertex mm (unseen mm).\n")
    lines.append("| body | " + " | ".join(methods) + " | best |")
    lines.append("|---|" + "---|" * (len(methods) + 1))
    for seed in sorted({r["seed"] for r in rows}):
        cell = {m: [r for r in rows if r["seed"] == seed and r["method"] == m] for m in methods}
        full = {m: c for m, c in cell.items() if len(c) == len(VIEWS)}
        mean = lambda m, key: np.mean([r["aligned"][key] for r in full[m]]) if m in full else np.nan  # noqa: E731
        best = min(full, key=lambda m: mean(m, "all")) if full else "-"
        lines.append(f"| {seed} | " + " | ".join(f"{mean(m, 'all'):.1f} ({mean(m, 'unseen'):.1f})" for m in methods)
                     + f" | {best} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=384)
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--candidates", default="", help=f"candidate schedules too: {', '.join(CANDIDATES)}")
    parser.add_argument("--seeds", default=",".join(map(str, SEEDS)))
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--report", action="store_true")
    parser.add_argument("--threads", type=int, default=2, help="--trace's thread count (the study's fits: 1)")
    parser.add_argument("--trace", metavar="SEED,YAW", help="trace one fit of --methods' first method instead")
    parser.add_argument("--align-shape-lr", type=float, help="the rigid alignment's step on the coefficients "
                        "(default: the shipped SHAPE_LR); rows go to study_body_align_shape_lr<X>.json")
    args = parser.parse_args()
    if args.align_shape_lr is not None and not 0 < args.align_shape_lr < 10:   # also refuses NaN
        parser.error(f"--align-shape-lr must be a step between 0 and 10, got {args.align_shape_lr}")
    results = results_file(args.align_shape_lr)
    if args.report:
        print(report(done_rows(results)))
        return
    if args.trace:
        seed, yaw = args.trace.split(",")
        trace(int(seed), float(yaw), args.methods.split(",")[0], args.size, threads=args.threads)
        return
    body_model()  # build the cache once, before the workers
    done = {(r["seed"], r["yaw"], r["method"], r["size"]) for r in done_rows(results)}
    methods = [m for m in args.methods.split(",") if m] + [f"candidate:{c}" for c in args.candidates.split(",") if c]
    tasks = [(seed, yaw, pitch, method, args.size) for method in methods
             for seed in map(int, args.seeds.split(",")) for yaw, pitch in VIEWS
             if (seed, yaw, method, args.size) not in done]
    results.parent.mkdir(parents=True, exist_ok=True)
    with ProcessPoolExecutor(args.workers) as pool:
        for row in pool.map(partial(run_case, align_shape_lr=args.align_shape_lr), tasks):
            with results.open("a") as handle:
                handle.write(json.dumps(row) + "\n")
            print(f"{row['method']:12s} seed {row['seed']} yaw {row['yaw']:5.0f}: all {row['aligned']['all']:.1f} mm "
                  f"(raw {row['raw']['all']:.1f}), unseen {row['aligned']['unseen']:.1f}, {row['seconds']:.0f} s", flush=True)


if __name__ == "__main__":
    main()
