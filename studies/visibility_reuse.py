"""The render fit's visibility reused between refreshes (docs/studies.md §26): the same default fits with
the renderer's visibility (which pixel shows which triangle, the silhouette pairs and the edges they
cross) refreshed every call and every K calls (``statfit.render.visibility.VISIBILITY_EVERY``).

Chosen on ICT's jaw-open and smile maps at 512² (benchmarks/cases.py; K = 1, 2, 3, 4: the largest K
with both errors within 1% of K = 1); checked, K = 1 against the chosen K, on §22's sets: the four
ICT rendering-study cases (256²), §18's cross-family cases (256²) and the body study's twelve views
(384²). One thread a fit, two fits side by side; the error in each set's unit
(studies/alignment_settle.py), the whole fit's seconds.

    python studies/visibility_reuse.py            # ~45 min on 2 cores
    python studies/visibility_reuse.py --report
"""
from __future__ import annotations

import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from adaptive_choice import single_threaded  # noqa: E402
from alignment_settle import SETS, UNITS, _fit  # noqa: E402
from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "visibility_reuse.json"
CHOSEN = ("jaw-open", "smile")
CANDIDATES = (1, 2, 3, 4)
CHECKED = 4                      # the choice, checked on the other sets against 1
UNITS = {"chosen": "% of the radius ×100"} | UNITS


def fit(case_set: str, case: str, every: int) -> dict:
    single_threaded()
    import statfit.render.job as job
    import statfit.render.visibility as visibility

    # as measured here: the alignment reused the visibility too (since §31 it refreshes every call)
    with mock.patch.object(visibility, "VISIBILITY_EVERY", every), \
            mock.patch.object(visibility, "VISIBILITY_IN_ALIGNMENT", True):
        row = _chosen(case, job) if case_set == "chosen" else _fit(case_set, case, job)
    return {"set": case_set, "case": case, "every": every} | row


def _chosen(case: str, job) -> dict:
    """ICT's ``case`` map at 512² (benchmarks/cases.py), the default fit: error over all vertices ÷
    the truth's RMS radius (×100) and seconds."""
    from cases import ict_model, normal_case, relative_errors

    named, model = normal_case(case, 512), ict_model()
    started = time.perf_counter()
    vertices = job.reconstruct(model, named.normal_map, named.camera, "default", threads=1).vertices
    error = 100 * relative_errors(vertices, named.target, named.observed)["all"]
    return {"error": error, "seconds": time.perf_counter() - started}


def runs() -> list[tuple]:
    chosen = [("chosen", case, every) for case in CHOSEN for every in CANDIDATES]
    return chosen + [(s, c, every) for s, cases in SETS.items() for c in cases for every in (1, CHECKED)]


def report(rows: list[dict]) -> str:
    by = {(r["set"], r["case"], r["every"]): r for r in rows}
    lines = ["| cases | error unit | K | error, every call | error, every K | every K ÷ every call: mean (range) | "
             "fit s (sum), every call → every K |", "|---|---|---|---|---|---|---|"]
    for case_set, cases in ({"chosen": CHOSEN} | SETS).items():
        for every in CANDIDATES[1:] if case_set == "chosen" else (CHECKED,):
            both = [c for c in cases if (case_set, c, 1) in by and (case_set, c, every) in by]
            if not both:
                continue
            base, reused = [by[(case_set, c, 1)] for c in both], [by[(case_set, c, every)] for c in both]
            ratio = np.array([r["error"] / b["error"] for b, r in zip(base, reused)])
            lines.append(
                f"| {case_set} ({len(both)}) | {UNITS[case_set]} | {every} | {np.mean([r['error'] for r in base]):.4g} | "
                f"{np.mean([r['error'] for r in reused]):.4g} | {ratio.mean():.3f} ({ratio.min():.3f}–{ratio.max():.3f}) | "
                f"{sum(r['seconds'] for r in base):.0f} → {sum(r['seconds'] for r in reused):.0f} |")
    lines += ["", "Per case (every K ÷ every call, error): " + "; ".join(
        f"{k[0]} {k[1]} K={k[2]} {by[k]['error'] / by[(k[0], k[1], 1)]['error']:.3f}"
        for k in by if k[2] != 1 and (k[0], k[1], 1) in by)]
    return "\n".join(lines)


if __name__ == "__main__":
    study_main(__doc__, fit, runs, RESULTS, report, key=lambda r: (r["set"], r["case"], r["every"]))
