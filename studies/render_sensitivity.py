"""How far a render fit's error moves for nothing (docs/studies.md §28): the default fit of §22's cases
against the same fit with every target normal nudged by ~1e-6 (Gaussian, renormalised; far below
any map's precision). What that moves is the floor under which a change of the fit (§26's and §27's
reused visibility) cannot be told from chance, case by case.

The four ICT rendering-study cases (256²), §18's cross-family cases (256²) and the body study's
twelve views (384²); one thread a fit, two fits side by side; the error in each set's unit
(studies/alignment_settle.py).

    python studies/render_sensitivity.py            # ~20 min on 2 cores
    python studies/render_sensitivity.py --report
"""
from __future__ import annotations

import contextlib
import sys
from pathlib import Path
from unittest import mock

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from adaptive_choice import single_threaded  # noqa: E402
from alignment_settle import SETS, UNITS, _fit  # noqa: E402
from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "render_sensitivity.json"
NUDGE = 1e-6


def nudging(job, nudge: float):
    """A context in which ``job``'s target normals are nudged by ``nudge`` (Gaussian, seed 1,
    renormalised; 0: as given)."""
    given = job.camera_space_normals

    def nudged(normal_map, *args, **kwargs):
        normals = given(normal_map, *args, **kwargs)
        noise = np.random.default_rng(1).standard_normal(normals.shape) * nudge
        moved = normals + noise * normal_map.mask[..., None]
        length = np.linalg.norm(moved, axis=-1, keepdims=True)
        return np.where(normal_map.mask[..., None], moved / np.maximum(length, 1e-12), normals)

    return mock.patch.object(job, "camera_space_normals", nudged) if nudge else contextlib.nullcontext()


def fit(case_set: str, case: str, nudge: float) -> dict:
    """One case's default fit, its target normals nudged by ``nudge`` (0: as given)."""
    single_threaded()
    import statfit.render.job as job

    with nudging(job, nudge):
        return {"set": case_set, "case": case, "nudge": nudge} | _fit(case_set, case, job)


def runs() -> list[tuple]:
    return [(s, c, nudge) for s, cases in SETS.items() for c in cases for nudge in (0.0, NUDGE)]


def report(rows: list[dict]) -> str:
    by = {(r["set"], r["case"], r["nudge"]): r for r in rows}
    lines = ["| cases | error unit | error, as given | error, nudged | nudged ÷ as given: mean (range) | "
             "mean |ratio − 1| | moved by > 2% |", "|---|---|---|---|---|---|---|"]
    for case_set, cases in SETS.items():
        both = [c for c in cases if (case_set, c, 0.0) in by and (case_set, c, NUDGE) in by]
        if not both:
            continue
        base, nudged = [by[(case_set, c, 0.0)] for c in both], [by[(case_set, c, NUDGE)] for c in both]
        ratio = np.array([n["error"] / b["error"] for b, n in zip(base, nudged)])
        lines.append(f"| {case_set} ({len(both)}) | {UNITS[case_set]} | {np.mean([r['error'] for r in base]):.4g} | "
                     f"{np.mean([r['error'] for r in nudged]):.4g} | {ratio.mean():.3f} ({ratio.min():.3f}–{ratio.max():.3f}) | "
                     f"{np.abs(ratio - 1).mean():.3f} | {int((np.abs(ratio - 1) > 0.02).sum())} |")
    lines += ["", "Per case (nudged ÷ as given): " + "; ".join(
        f"{k[0]} {k[1]} {by[k]['error'] / by[(k[0], k[1], 0.0)]['error']:.3f}"
        for k in by if k[2] == NUDGE and (k[0], k[1], 0.0) in by)]
    return "\n".join(lines)


if __name__ == "__main__":
    study_main(__doc__, fit, runs, RESULTS, report, key=lambda r: (r["set"], r["case"], r["nudge"]))
