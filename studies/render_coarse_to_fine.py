"""Faster schedules for ``statfit render``'s default fit: coarse-to-fine image resolution, fewer
iterations, larger early steps, a pca (Adam on coefficients) start.

The four rendering-study cases (benchmarks/study_render.py: same identities, expressions and views)
rendered at 512². A schedule is a list of levels (image size, stages); the first level runs
``reconstruct`` with the default rigid alignment on the map reduced to its size (the alignment
itself works on at most ~256 px), every later level continues from the previous vertices with
``align="none"``. Maps are reduced with ``statfit.render.job.downsampled`` (integer factors of
512; world-space normals average and renormalise the same as camera-space ones). Error: mean
per-vertex distance to the ground truth over all vertices / its RMS radius (benchmarks/cases.py
``relative_errors``); seconds: the fit calls only (alignment and setup included, target rendering
and error evaluation not). One thread, one process. The error is also traced every 100 iterations
(``on_snapshot``) so a truncated run's error can be read off.

Finding (this CPU, one thread, the other core busy): coarse levels save little per iteration
(~32 ms at 512², ~22 ms at 256² and 128²: rasterising and filtering the mesh dominate) and end
worse (jaw-open plateaus at 0.039 from 256², 0.042 from 128²); neither a larger step nor Adam's β2
speeds up the default's slow late phase. The off-model gain does: β 10 reaches the default's
3000-iteration error in ~300–450 iterations, but alone it overshoots brow-up; β 30 first, then β 10,
meets the default on all four cases in < 30 s ("512: hyb 150 lr .05 → hyb 300 lr .05 β10").

    python studies/render_coarse_to_fine.py [--schedules a,b|all] [--cases a,b]   # measure (cached)
    python studies/render_coarse_to_fine.py --report                          # markdown table
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from cases import ict_model, relative_errors  # noqa: E402
from common import ICT_EXPRESSIONS  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "render_coarse_to_fine.json"
SIZE = 512
CASE_NAMES = ("jaw-open", "smile", "brow-up", "puff")
TRACE_EVERY = 100
# Measured on all four cases by a plain run; the rest were screened on two cases (--schedules all).
FINALISTS = ("default (shipped)", "512: hyb 450 lr .03 β10", "512: hyb 150 lr .05 → hyb 300 lr .05 β10",
             "512: hyb 200 lr .03 → hyb 300 lr .05 β10")


def schedules() -> dict:
    """name → ((image size, (Settings, ...)), ...)."""
    from statfit.core.methods import Settings

    def hyb(iterations: int, lr: float = 0.01, b2: float = 0.999, **kw) -> Settings:
        return Settings("hybrid", iterations, lr, **({"beta": 30.0, "lam": 19.0, "mode_gain": 1.0} | kw),
                        adam_betas=(0.9, b2))

    def pca(iterations: int, lr: float = 0.05) -> Settings:
        return Settings("pca", iterations, lr)

    return {
        "default (shipped)": ((512, (hyb(3000),)),),  # RENDER default: hybrid β 30, λ 19, γ 1, lr 0.01
        # screening (jaw-open, smile)
        "512: hyb 500 lr .03": ((512, (hyb(500, 0.03),)),),
        "256: hyb 800 lr .03 → 512: hyb 100": ((256, (hyb(800, 0.03),)), (512, (hyb(100),))),
        "256: hyb 800 lr .05 → 512: hyb 100": ((256, (hyb(800, 0.05),)), (512, (hyb(100),))),
        "256: hyb 500 lr .05 → hyb 300 lr .02 → 512: hyb 100": ((256, (hyb(500, 0.05), hyb(300, 0.02))),
                                                               (512, (hyb(100),))),
        "128: hyb 800 lr .03 → 512: hyb 100": ((128, (hyb(800, 0.03),)), (512, (hyb(100),))),
        "256: pca 300 lr .1 → hyb 500 lr .03 → 512: hyb 100": ((256, (pca(300, 0.1), hyb(500, 0.03))),
                                                              (512, (hyb(100),))),
        "512: hyb 600 lr .03 b2 .99": ((512, (hyb(600, 0.03, 0.99),)),),
        "512: hyb 600 lr .01 b2 .99": ((512, (hyb(600, 0.01, 0.99),)),),
        "512: hyb 600 lr .03 b2 .9": ((512, (hyb(600, 0.03, 0.9),)),),
        "512: hyb 300 lr .05 → hyb 300 lr .01": ((512, (hyb(300, 0.05), hyb(300))),),
        "512: hyb 600 lr .03 β10": ((512, (hyb(600, 0.03, beta=10.0),)),),
        "512: hyb 600 lr .03 β3": ((512, (hyb(600, 0.03, beta=3.0),)),),
        "512: hyb 600 lr .03 γ.5": ((512, (hyb(600, 0.03, mode_gain=0.5),)),),
        # finalists (β 10: off-model gain 1/11 instead of 1/31)
        "512: hyb 450 lr .03 β10": ((512, (hyb(450, 0.03, beta=10.0),)),),
        "256: hyb 400 lr .03 β10 → 512: hyb 150 lr .03 β10": ((256, (hyb(400, 0.03, beta=10.0),)),
                                                             (512, (hyb(150, 0.03, beta=10.0),))),
        "512: hyb 400 lr .05 β10": ((512, (hyb(400, 0.05, beta=10.0),)),),
        "512: hyb 450 lr .03 β20": ((512, (hyb(450, 0.03, beta=20.0),)),),
        "512: hyb 200 lr .03 → hyb 250 lr .03 β10": ((512, (hyb(200, 0.03), hyb(250, 0.03, beta=10.0))),),
        "512: hyb 150 lr .05 → hyb 300 lr .05 β10": ((512, (hyb(150, 0.05), hyb(300, 0.05, beta=10.0))),),
        "512: hyb 200 lr .03 → hyb 300 lr .05 β10": ((512, (hyb(200, 0.03), hyb(300, 0.05, beta=10.0))),),
    }


def make_case(name: str):
    """(ground truth, 512² NormalMap, camera, visible-vertex mask) of a rendering-study case."""
    from study_render import CASES, make_target

    from statfit.geometry.metrics import visible_vertices

    case = next(c for c in CASES if c.name == name)
    gt, camera, normal_map = make_target(ict_model(), ICT_EXPRESSIONS, case, SIZE)
    return gt, normal_map, camera, visible_vertices(gt, ict_model().faces, camera, normal_map.mask)


def reduced(normal_map, camera, size: int):
    """The map and camera reduced to ``size`` (an integer factor of the map's size)."""
    import numpy as np
    import torch

    from statfit.render.job import downsampled
    from statfit.structures.normal_map import NormalMap

    if size >= min(normal_map.mask.shape):
        return normal_map, camera
    normals, mask, small = downsampled(torch.as_tensor(normal_map.normals, dtype=torch.float64),
                                       torch.as_tensor(normal_map.mask), camera, size)
    return NormalMap(normals.numpy().astype(np.float32), mask.numpy()), small


def run(schedule, gt, normal_map, camera, visible) -> dict:
    """Fit with ``schedule``; the all/visible/hidden errors, seconds and the error trace."""
    from statfit.render.job import reconstruct

    model = ict_model()
    trace, seconds, level_seconds, done = [], 0.0, [], 0
    vertices = None
    for size, stages in schedule:
        small_map, small_camera = reduced(normal_map, camera, size)
        offset = done

        def snapshot(it: int, x, offset=offset) -> None:
            if it % TRACE_EVERY == 0:
                trace.append((offset + it, relative_errors(x, gt, visible)["all"]))

        kwargs = {} if vertices is None else {"init": vertices, "align": "none"}
        started = time.perf_counter()
        fit = reconstruct(model, small_map, small_camera, stages=stages, threads=1, on_snapshot=snapshot, **kwargs)
        level_seconds.append(time.perf_counter() - started)
        seconds += level_seconds[-1]
        vertices = fit.vertices
        done += sum(s.iterations for s in stages)
    errors = relative_errors(vertices, gt, visible)
    return {"all": errors["all"], "visible": errors["observed"], "hidden": errors["unobserved"],
            "seconds": seconds, "level_seconds": level_seconds, "trace": trace}


def describe(schedule) -> list:
    """The schedule as plain lists (the cache key): per level, its size and per stage the
    settings that vary here."""
    keys = ("method", "iterations", "lr", "beta", "lam", "mode_gain")
    def one(s) -> list:
        return [getattr(s, k) for k in keys] + ([] if s.adam_betas == (0.9, 0.999) else [list(s.adam_betas)])

    return [[size, [one(s) for s in stages]] for size, stages in schedule]


def load() -> list[dict]:
    return json.loads(RESULTS.read_text()) if RESULTS.exists() else []


def report(results: list[dict]) -> str:
    names = list(schedules()) + sorted({r["schedule"] for r in results} - set(schedules()))
    base = {r["case"]: r for r in results if r["schedule"] == "default (shipped)"}
    lines = ["| schedule | " + " | ".join(CASE_NAMES) + " | mean all | worst vs default | s/fit (mean, max) |",
             "|---" * (len(CASE_NAMES) + 4) + "|"]
    for name in names:
        rows = {r["case"]: r for r in results if r["schedule"] == name}
        if not rows:
            continue
        cells = [f"{rows[c]['all']:.4f} ({rows[c]['seconds']:.0f} s)" if c in rows else "–" for c in CASE_NAMES]
        ratios = [rows[c]["all"] / base[c]["all"] for c in rows if c in base]
        worst = f"{max(ratios) - 1:+.1%}" if ratios else "–"
        mean = sum(r["all"] for r in rows.values()) / len(rows)
        secs = [r["seconds"] for r in rows.values()]
        partial = "" if len(rows) == len(CASE_NAMES) else f" ({len(rows)} cases)"
        lines.append(f"| {name}{partial} | " + " | ".join(cells)
                     + f" | {mean:.4f} | {worst} | {sum(secs) / len(secs):.1f}, {max(secs):.1f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--schedules", default=None,
                        help="comma-separated names, or 'all' (default: the default and the finalists)")
    parser.add_argument("--cases", default=",".join(CASE_NAMES))
    parser.add_argument("--report", action="store_true")
    args = parser.parse_args()
    if args.report:
        print(report(load()))
        return
    import torch

    torch.set_num_threads(1)
    table = schedules()
    names = (list(table) if args.schedules == "all" else args.schedules.split(",") if args.schedules
             else list(FINALISTS))
    for case_name in args.cases.split(","):
        data = None
        for name in names:
            spec = describe(table[name])
            if any(r["case"] == case_name and r["schedule"] == name and r["spec"] == spec for r in load()):
                continue
            data = data or make_case(case_name)
            row = run(table[name], *data) | {"case": case_name, "schedule": name, "spec": spec}
            print(json.dumps({k: v for k, v in row.items() if k not in ("trace", "spec")}), flush=True)
            RESULTS.parent.mkdir(exist_ok=True)
            kept = [r for r in load() if not (r["case"] == case_name and r["schedule"] == name)]
            RESULTS.write_text(json.dumps(kept + [row], indent=1))


if __name__ == "__main__":
    main()
