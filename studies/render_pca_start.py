"""A span-first start for ``statfit render``: does a pca stage before the default's two hybrid stages
help faces as it helps bodies (docs/studies.md §13, §17)?

The rendering study's four ICT cases (studies/study_render.py: same identities, expressions and
views) at 512², each fitted by the render default of session 7 and by the candidate below, side by
side in one run (one thread per fit, two fits at a time). Error: mean per-vertex distance to the
ground truth over all vertices / its RMS radius (benchmarks/cases.py ``relative_errors``), as in §11.

    PYTHONPATH=. python studies/render_pca_start.py [--schedules a,b] [--workers 2]   # measure (cached)
    PYTHONPATH=. python studies/render_pca_start.py --report                          # markdown table
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "studies"))

from cases import ict_model, relative_errors  # noqa: E402
from common import ICT_EXPRESSIONS  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "render_pca_start.json"
SIZE = 512
CASE_NAMES = ("jaw-open", "smile", "brow-up", "puff")
# name (as the results record it) → its stages: the render default of the time (session 7: two hybrid
# stages) and the candidate shipped then as the opt-in span-first (500 pca steps under the prior 0.1,
# then those two stages; withdrawn in session 9, docs/studies.md §13). Both from the rigid alignment
# of the time, whose step on the coefficients was the pose's (ALIGN_SHAPE_LR).
ALIGN_SHAPE_LR = 0.01
_HYBRID = {"lam": 19.0, "mode_gain": 1.0}
SCHEDULES = {"default (shipped)": (("hybrid", 150, 0.05, {"beta": 30.0, **_HYBRID}),
                                   ("hybrid", 300, 0.05, {"beta": 10.0, **_HYBRID})),
             "pca 500 (prior 0.1) → default": (("pca", 500, 0.05, {"prior": 0.1}),
                                               ("hybrid", 150, 0.05, {"beta": 30.0, **_HYBRID}),
                                               ("hybrid", 300, 0.05, {"beta": 10.0, **_HYBRID}))}


def stages(name: str):
    from statfit.core.settings import Settings

    return tuple(Settings(method, iterations, lr, **extra) for method, iterations, lr, extra in SCHEDULES[name])


def run_case(task: tuple[str, str]) -> dict:
    """One fit of one case with one schedule: its errors and seconds."""
    case_name, schedule = task
    import torch

    torch.set_num_threads(1)
    import statfit.render.job
    from study_render import CASES, make_target

    statfit.render.job.SHAPE_LR = ALIGN_SHAPE_LR

    from statfit.render.job import reconstruct
    from statfit.geometry.metrics import visible_vertices

    model = ict_model()
    case = next(c for c in CASES if c.name == case_name)
    gt, camera, normal_map = make_target(model, ICT_EXPRESSIONS, case, SIZE)
    visible = visible_vertices(gt, model.faces, camera, normal_map.mask)
    started = time.perf_counter()
    fit = reconstruct(model, normal_map, camera, stages=stages(schedule), threads=1)
    errors = relative_errors(fit.vertices, gt, visible)
    return {"case": case_name, "schedule": schedule, "all": errors["all"], "visible": errors["observed"],
            "hidden": errors["unobserved"], "seconds": time.perf_counter() - started}


def load() -> list[dict]:
    return [json.loads(line) for line in RESULTS.read_text().splitlines()] if RESULTS.exists() else []


def report(rows: list[dict]) -> str:
    lines = ["| schedule | " + " | ".join(CASE_NAMES) + " | mean | s per fit |", "|---" * (len(CASE_NAMES) + 3) + "|"]
    for name in SCHEDULES:
        mine = {r["case"]: r for r in rows if r["schedule"] == name}
        if not mine:
            continue
        cells = [f"{mine[c]['all']:.4f}" if c in mine else "–" for c in CASE_NAMES]
        mean = sum(r["all"] for r in mine.values()) / len(mine)
        seconds = sum(r["seconds"] for r in mine.values()) / len(mine)
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {mean:.4f} | {seconds:.0f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--schedules", default=",".join(SCHEDULES))
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--report", action="store_true")
    args = parser.parse_args()
    if args.report:
        print(report(load()))
        return
    done = {(r["case"], r["schedule"]) for r in load()}
    tasks = [(case, name) for name in args.schedules.split(",") for case in CASE_NAMES if (case, name) not in done]
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    with ProcessPoolExecutor(args.workers) as pool:
        for row in pool.map(run_case, tasks):
            with RESULTS.open("a") as handle:
                handle.write(json.dumps(row) + "\n")
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
