"""The render alignment's early stop (docs/studies.md §22): the same fits with the alignment's 200
iterations run in full and stopped once settled (``statfit.render.job.POSE_SETTLE``: the best value
fell by less than 0.1% over 25 iterations).

Cases, all with ``render``'s default method and alignment, one thread: the four ICT rendering-study
cases (studies/study_render.py, 256²; error over all vertices ÷ the truth's RMS radius), §18's
cross-family cases (studies/cross_family_render.py: 3 families × 3 models × 2 people, 256²; mean
distance of the person's surface to the fit, % of their RMS radius) and the body study's twelve
views (studies/study_body.py, 384²; mm over all vertices). Reported per set: the error both ways,
the alignment's and the whole fit's seconds.

    python studies/alignment_settle.py            # ~35 min on 2 cores
    python studies/alignment_settle.py --report
"""
from __future__ import annotations

import argparse
import contextlib
import sys
import time
from unittest import mock
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from adaptive_choice import single_threaded  # noqa: E402
from study_runs import run_or_report  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "alignment_settle.json"
FAMILIES = ("ict", "ict-mask", "makehuman")
SETS = {"ict": ("jaw-open", "smile", "brow-up", "puff"),
        "cross": tuple(f"{p}/{m}/{s}" for p in FAMILIES for m in FAMILIES for s in (0, 1)),
        "body": tuple(f"{seed}/{yaw:g}" for seed in (1, 2, 3, 4, 5, 6) for yaw in (30.0, -60.0))}
UNITS = {"ict": "% of the radius ×100", "cross": "% of the radius", "body": "mm"}


def fit(case_set: str, case: str, settled: bool) -> dict:
    single_threaded()
    import statfit.render.job as job

    # a pool's worker runs many cases: the full run's setting is undone after the fit
    with contextlib.nullcontext() if settled else mock.patch.object(job, "POSE_SETTLE", None):
        return {"set": case_set, "case": case, "settled": settled} | _fit(case_set, case, job)


def _fit(case_set: str, case: str, job) -> dict:
    """One case's default fit: its error (the set's unit), whole and alignment seconds."""
    from statfit.core.fit import StageTimer

    timer = StageTimer()
    started = time.perf_counter()
    if case_set == "ict":
        import study_render
        from common import ICT, ICT_MODEL
        from statfit.geometry.metrics import visible_vertices
        from statfit.model.statmodel import load_model

        model = load_model(ICT_MODEL)
        spec = next(c for c in study_render.CASES if c.name == case)
        truth, camera, normal_map = study_render.make_target(model, ICT / "ict_face_expressions.npz", spec, 256)
        vertices = job.reconstruct(model, normal_map, camera, "default", threads=1, timer=timer).vertices
        error = 100 * study_render.errors(vertices, truth, visible_vertices(truth, model.faces, camera))["all"]
    elif case_set == "cross":
        from cross_family import inside_distance
        from cross_family_render import render_case
        from families import family_model
        from statfit.structures.frame import Frame

        people, model_family, seed = case.split("/")
        shape, normal_map, camera, points, _ = render_case(people, model_family, int(seed), 256)
        model = family_model(model_family)
        vertices = job.reconstruct(model, normal_map, camera, "default", threads=1, timer=timer).vertices
        error = float(np.nanmean(100.0 * inside_distance(points, vertices, model.faces) / Frame.of(shape).scale))
    else:
        import study_body

        seed, yaw = case.split("/")
        pitch = dict(study_body.VIEWS)[float(yaw)]
        model, truth, camera, normal_map = study_body.view(int(seed), float(yaw), pitch, 384)
        vertices = job.reconstruct(model, normal_map, camera, "default", threads=1, timer=timer,
                                   **study_body.schedule("default")).vertices
        error = float(np.linalg.norm(vertices - truth, axis=1).mean() * 1000)
    return {"error": error, "seconds": time.perf_counter() - started, "alignment": timer.seconds.get("alignment", 0.0)}


def report(rows: list[dict]) -> str:
    by = {(r["set"], r["case"], r["settled"]): r for r in rows}
    lines = ["| cases | error unit | error, full 200 | error, settled | settled ÷ full: mean (range) | "
             "alignment s (sum), full → settled | fit s (sum), full → settled |", "|---|---|---|---|---|---|---|"]
    for case_set, cases in SETS.items():
        both = [c for c in cases if (case_set, c, False) in by and (case_set, c, True) in by]
        if not both:
            continue
        full = [by[(case_set, c, False)] for c in both]
        settled = [by[(case_set, c, True)] for c in both]
        ratio = np.array([s["error"] / f["error"] for f, s in zip(full, settled)])
        total = lambda rows, key: sum(r[key] for r in rows)  # noqa: E731
        lines.append(f"| {case_set} ({len(both)}) | {UNITS[case_set]} | {np.mean([r['error'] for r in full]):.4g} | "
                     f"{np.mean([r['error'] for r in settled]):.4g} | {ratio.mean():.3f} ({ratio.min():.3f}–{ratio.max():.3f}) | "
                     f"{total(full, 'alignment'):.0f} → {total(settled, 'alignment'):.0f} | "
                     f"{total(full, 'seconds'):.0f} → {total(settled, 'seconds'):.0f} |")
    lines += ["", "Per case (settled ÷ full error): " + "; ".join(
        f"{k[1]} {by[(k[0], k[1], True)]['error'] / by[(k[0], k[1], False)]['error']:.3f}"
        for k in by if k[2] and (k[0], k[1], False) in by)]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sets", nargs="*", default=list(SETS), help=f"of {', '.join(SETS)}")
    parser.add_argument("--report", action="store_true", help="only print the table of the stored rows")
    args = parser.parse_args()
    runs = [(s, c, settled) for s in args.sets for c in SETS[s] for settled in (False, True)]
    run_or_report(fit, runs, RESULTS, report, args.report, key=lambda r: (r["set"], r["case"], r["settled"]))


if __name__ == "__main__":
    main()
