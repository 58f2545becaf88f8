"""Splatting on a mesh (issue 15's study): photographs of ICT heads with an expression the model
does not have, fitted by every method through the splatting loss.

Cases: ICT identity samples (seeds 1..4, coefficients ~ N(0, 1)) plus one ICT expression each
(jawOpen, mouthSmile_R, browInnerUp_L, mouthLeft: blendshapes the identity model never saw), with
a generated albedo and a fixed light (``statfit synth views``), 24 cameras over the front
hemisphere at 256², every 6th held out (4 test views). Every method at its tuned splat setting
(``resolve(method, job="splat")``: the same iteration budget for all), one splat per triangle.

Metrics: mean vertex error relative to the truth's RMS radius, over all vertices, the vertices
seen by at least 3 training cameras ("seen") and those seen by 1 or 2 ("barely seen": the outline
region the paper's ghosting lives in); held-out-view PSNR and SSIM of the splats rendered at the
fit; seconds.

Results are appended to ``studies/results/study_splat.json`` after every fit (a rerun resumes);
``--report`` prints the Markdown table of docs/studies.md. From the repository root:

    PYTHONPATH=. python studies/study_splat.py [--methods a,b] [--workers 2] [--report]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from common import ICT_EXPRESSIONS, ICT_MODEL  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "study_splat.json"
CASES = ((1, "jawOpen"), (2, "mouthSmile_R"), (3, "browInnerUp_L"), (4, "mouthLeft"))
METHODS = ("default", "statistical", "hybrid", "laplacian", "pca", "none")
VIEWS, SIZE, TEST_EVERY = 24, 256, 6


def make_case(seed: int, expression: str):
    """Truth (N, 3), faces, the views, and how many training cameras see each vertex (N,)."""
    from statfit.model.importers.cache import open_model
    from statfit.geometry.metrics import visible_vertices
    from statfit.synth.sample import load_delta
    from statfit.synth.views import generated_albedo, held_out_split, hemisphere_cameras
    from statfit.renderer.images import photograph
    from statfit.structures.views import View

    model = open_model(ICT_MODEL)
    rng = np.random.default_rng(seed)
    truth = model.sample(rng, 1.0) + load_delta(str(ICT_EXPRESSIONS), expression)
    albedo = generated_albedo(truth, rng)
    views, seen = [], np.zeros(len(truth), dtype=int)
    for index, (camera, split) in enumerate(zip(hemisphere_cameras(truth, VIEWS, SIZE),
                                                held_out_split(VIEWS, TEST_EVERY))):
        colour, alpha = photograph(truth, model.faces, albedo, camera)
        views.append(View(f"view_{index:03d}", camera, colour, alpha > 0.5, split))
        if split == "train":
            seen += visible_vertices(truth, model.faces, camera)
    return model, truth, views, seen


def run_one(job: tuple[int, str, str]) -> dict:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    from statfit.structures.frame import Frame
    from statfit.splat.job import fit_views

    torch.set_num_threads(1)
    seed, expression, method = job
    model, truth, views, seen = make_case(seed, expression)
    started = time.perf_counter()
    result = fit_views(model, views, method, threads=1)
    seconds = time.perf_counter() - started
    error = np.linalg.norm(result.fit.vertices - truth, axis=1) / Frame.of(truth).scale
    start_error = np.linalg.norm(model.template - truth, axis=1) / Frame.of(truth).scale
    groups = {"all": np.ones(len(truth), bool), "seen": seen >= 3, "barely_seen": (seen >= 1) & (seen <= 2)}
    held_out = result.mean_scores("test")
    return {"seed": seed, "expression": expression, "method": method, "seconds": seconds,
            **{f"error_{name}": float(error[mask].mean()) for name, mask in groups.items()},
            **{f"template_{name}": float(start_error[mask].mean()) for name, mask in groups.items()},
            "psnr": held_out["psnr"], "ssim": held_out["ssim"], "train_psnr": result.mean_scores("train")["psnr"]}


def load() -> list[dict]:
    return json.loads(RESULTS.read_text()) if RESULTS.exists() else []


def report(rows: list[dict]) -> str:
    """The table over the cases every method has finished (a partial case would bias the means)."""
    methods = [m for m in METHODS if any(r["method"] == m for r in rows)]
    complete = {(r["seed"], r["expression"]) for r in rows
                if all(any(o["method"] == m and (o["seed"], o["expression"]) == (r["seed"], r["expression"])
                           for o in rows) for m in methods)}
    rows = [r for r in rows if (r["seed"], r["expression"]) in complete]
    lines = ["| method | all % | seen % | barely seen % | held-out PSNR dB | SSIM | s / fit | best PSNR (cases) |",
             "|---|---|---|---|---|---|---|---|"]
    cases = sorted({(r["seed"], r["expression"]) for r in rows})
    best = {}
    for case in cases:
        here = [r for r in rows if (r["seed"], r["expression"]) == case]
        best[case] = max(here, key=lambda r: r["psnr"])["method"]
    for method in methods:
        mine = [r for r in rows if r["method"] == method]
        mean = lambda key: np.mean([r[key] for r in mine])  # noqa: E731
        lines.append(f"| {method} | {100 * mean('error_all'):.2f} | {100 * mean('error_seen'):.2f} | "
                     f"{100 * mean('error_barely_seen'):.2f} | {mean('psnr'):.2f} | {mean('ssim'):.4f} | "
                     f"{mean('seconds'):.0f} | {sum(v == method for v in best.values())} of {len(cases)} |")
    template = [r for r in rows if r["method"] == methods[0]]
    lines.append(f"| (template, no fit) | {100 * np.mean([r['template_all'] for r in template]):.2f} | "
                 f"{100 * np.mean([r['template_seen'] for r in template]):.2f} | "
                 f"{100 * np.mean([r['template_barely_seen'] for r in template]):.2f} | | | | |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--report", action="store_true")
    args = parser.parse_args()
    rows = load()
    if args.report:
        print(report(rows))
        return
    done = {(r["seed"], r["expression"], r["method"]) for r in rows}
    jobs = [(seed, expression, method) for seed, expression in CASES for method in args.methods.split(",")
            if (seed, expression, method) not in done]
    with ProcessPoolExecutor(args.workers) as pool:
        for row in pool.map(run_one, jobs):
            rows.append(row)
            RESULTS.write_text(json.dumps(rows, indent=1) + "\n")
            print(f"{row['seed']} {row['expression']:14s} {row['method']:12s} all {100 * row['error_all']:.2f}% "
                  f"PSNR {row['psnr']:.2f} ({row['seconds']:.0f} s)", flush=True)
    print(report(rows))


if __name__ == "__main__":
    main()
