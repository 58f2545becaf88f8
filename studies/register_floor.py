"""How far a nudge moves register's held-out guess at today's code, and what calms it at what cost
(docs/studies.md §49): §29's protocol (studies/register_sensitivity.py: §19's 72 cross-family
held-out-half cases, each fitted as given and with its seen points nudged by 1e-4 mm) under variants
of the pose that the seen half's landmarks place and the scan polishes
(:func:`statfit.registration.pose.search.refine_pose`, 12 Gauss–Newton steps on the pose and every
mode):

- ``shipped``: as it ships;
- ``polish settles``: that polish goes on while it moves or its objective falls (§41, §48's rule);
- ``polish prior 0.03`` / ``0.1``: its prior on the modes 3× / 10× stronger (``POLISH_NOISE`` 0.01);
- ``polish averaged``: four polishes, each of another random subsample of the scan's points, their
  rotations (the nearest rotation to their mean), shifts and coefficients averaged.

and ``mean``, the model's mean placed by the landmarks (no fit: the bar of issue 37's per-case target).
One thread a fit, two side by side; ``held`` in mm.

    python studies/register_floor.py            # ~30 min on 2 cores
    python studies/register_floor.py --report
"""
from __future__ import annotations

import functools
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import register_sensitivity as floor  # noqa: E402
from families import LANDMARKED  # noqa: E402
from study_runs import study_main  # noqa: E402

if TYPE_CHECKING:
    from statfit.geometry.align import Similarity
    from statfit.model.statmodel import StatModel
    from statfit.registration.pose.search import PoseEstimate
    from statfit.structures.scan import Scan

RESULTS = ROOT / "studies" / "results" / "register_floor.json"
VARIANTS = ("shipped", "polish settles", "polish prior 0.03", "polish prior 0.1", "polish averaged")
AVERAGED = 4
OVER_MEAN = 1.1     # issue 37's per-case bound: no case worse than the unfitted mean by more than 10%


def under_variant(variant: str, run: Callable[[], dict]) -> dict:
    """``run()`` with the landmark-placed pose's polish patched to ``variant``, restored after: a
    spawned worker runs cases of several variants in turn."""
    from statfit.registration import prealign
    from statfit.registration.pose import refinement, search

    shipped = search.polish_pose, refinement.POLISH_NOISE, prealign.refine_pose
    if variant == "polish settles":
        search.polish_pose = functools.partial(refinement.polish_pose, settle=True)
    elif variant.startswith("polish prior "):
        refinement.POLISH_NOISE = float(variant.removeprefix("polish prior "))
    elif variant == "polish averaged":
        prealign.refine_pose = functools.partial(averaged_refine_pose, search.refine_pose)
    try:
        return run()
    finally:
        search.polish_pose, refinement.POLISH_NOISE, prealign.refine_pose = shipped


def averaged_refine_pose(refine_pose: Callable, model: StatModel, scan: Scan, start: Similarity,
                         seed: int = 0) -> PoseEstimate:
    """``refine_pose`` run AVERAGED times on other subsamples (seeds), the poses and coefficients averaged."""
    from dataclasses import replace

    from statfit.geometry.align import Similarity

    estimates = [refine_pose(model, scan, start, seed + k) for k in range(AVERAGED)]
    u, _, vt = np.linalg.svd(sum(e.transform.rotation for e in estimates))
    rotation = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    transform = Similarity(estimates[0].transform.scale, rotation,
                           np.mean([e.transform.translation for e in estimates], axis=0))
    return replace(estimates[0], transform=transform,
                   coefficients=np.mean([e.coefficients for e in estimates], axis=0))


def fit(variant: str, people: str, model_family: str, seed: int, half: str, nudge: float) -> dict:
    """One case under ``variant`` (or the landmark-placed ``mean``), its seen points nudged by ``nudge`` mm."""
    if variant == "mean":
        import cross_family_landmarks as protocol

        return protocol.fit_case(people, model_family, seed, half, "mean") | {"nudge": nudge, "variant": variant}
    return under_variant(variant, lambda: floor.fit(people, model_family, seed, half, nudge)) | {"variant": variant}


def runs() -> list[tuple]:
    cases = floor.runs()
    return [("mean", *case) for case in cases if case[-1] == 0.0] + [(v, *case) for v in VARIANTS for case in cases]


def report(rows: list[dict]) -> str:
    case = lambda r: (r["people"], r["model"], r["seed"], r["half"])  # noqa: E731
    means = {case(r): r["held"] for r in rows if r["variant"] == "mean" and "held" in r}
    variants = [v for v in VARIANTS if any(r["variant"] == v for r in rows)]
    held = {v: {(case(r), r["nudge"]): r["held"] for r in rows if r["variant"] == v and "held" in r} for v in variants}
    lines = [f"Per pair: held-out error (mm, mean of the fits as given and nudged) / mean |nudged ÷ given − 1| / "
             f"cases where either fit is over {OVER_MEAN}× the landmark-placed mean's.", "",
             "| people | model | mean (no fit) | " + " | ".join(variants) + " |",
             "|---|---|---|" + "---|" * len(variants)]
    summary = {v: [] for v in variants}
    for people in LANDMARKED:
        for model in LANDMARKED:
            cells = []
            pair = sorted(c for c in means if c[:2] == (people, model))
            for v in variants:
                both = [c for c in pair if (c, 0.0) in held[v] and (c, floor.NUDGE_MM) in held[v]]
                given = np.array([held[v][(c, 0.0)] for c in both])
                nudged = np.array([held[v][(c, floor.NUDGE_MM)] for c in both])
                bar = np.array([means[c] for c in both])
                summary[v] += list(zip(given, nudged, bar))
                cells.append(f"{(given.mean() + nudged.mean()) / 2:.2f} / {np.abs(nudged / given - 1).mean():.3f} / "
                             f"{int((np.maximum(given, nudged) > OVER_MEAN * bar).sum())}" if both else "–")
            if pair:
                lines.append(f"| {people} | {model} | {np.mean([means[c] for c in pair]):.2f} | "
                             + " | ".join(cells) + " |")
    lines += ["", "| variant | cases | held-out (mm) | mean \\|nudged ÷ given − 1\\| | moved by > 10% | "
                  f"over {OVER_MEAN}× the mean's (either fit) |", "|---|---|---|---|---|---|"]
    for v in variants:
        given, nudged, bar = np.array(summary[v]).T
        ratio = np.abs(nudged / given - 1)
        lines.append(f"| {v} | {len(given)} | {(given.mean() + nudged.mean()) / 2:.3f} | {ratio.mean():.4f} | "
                     f"{int((ratio > 0.1).sum())} | {int((np.maximum(given, nudged) > OVER_MEAN * bar).sum())} |")
    failed = [r for r in rows if "error" in r]
    if failed:
        lines += ["", f"{len(failed)} fits refused or failed: " + "; ".join(
            f"{r['variant']} {r['people']}/{r['model']}/{r['seed']}/{r['half']} {r['error']}" for r in failed)]
    return "\n".join(lines)


if __name__ == "__main__":
    study_main(__doc__, fit, runs, RESULTS, report,
               key=lambda r: (r["variant"], r["people"], r["model"], r["seed"], r["half"], r["nudge"]))
