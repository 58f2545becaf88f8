"""Choosing the method per scan from the scan itself (issue 37, part 3; docs/studies.md §20).

On §19's cases (studies/cross_family_landmarks.py: a half face of a person from one model family,
fitted with another family's model and that half's landmarks, scored on the other half), the
default and ``laplacian`` each win on some pairs. Can a fit tell, from the points it was given,
which one will guess the unseen part better? The rule tried here, which needs nothing but the scan
and its landmarks:

- place the model's mean by the landmarks and take the direction d from the scan's centroid towards
  the mean's (towards where the scan does not reach);
- hold out the quarter of the scan's points farthest along d (the scan's edge facing the unseen
  part) and fit each candidate method to the rest, with the landmarks;
- keep the candidate whose fit lies nearest the held-out quarter (mean distance to its surface).

The chosen method's error on the real test (the other half) is then §19's row of that method fitted
to the whole half (stored in studies/results/cross_family_landmarks.json): this study runs only the
validation fits. Reported per (people, model) pair: the mean held-out error of the default,
``laplacian``, the choice, the better of the two per case (the oracle), and how often the choice
agrees with the oracle.

    python studies/adaptive_choice.py --people 2      # ~10 min on 2 cores, after cross_family_landmarks.py
    python studies/adaptive_choice.py --report
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from cross_family import inside_distance  # noqa: E402
from cross_family_landmarks import HALVES, RESULTS as FULL_FITS, case_data  # noqa: E402
from families import LANDMARKED  # noqa: E402
from study_runs import run_or_report  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "adaptive_choice.json"
CANDIDATES = ("default", "laplacian")
HELD_SHARE = 0.25


def validation_split(points: np.ndarray, template_placed: np.ndarray) -> np.ndarray:
    """(M,) bool: the HELD_SHARE of ``points`` (M, 3) farthest along the direction from their
    centroid towards the placed template's (N, 3) centroid."""
    direction = template_placed.mean(axis=0) - points.mean(axis=0)
    direction /= max(np.linalg.norm(direction), 1e-12)
    along = points @ direction
    return along >= np.quantile(along, 1.0 - HELD_SHARE)


def fit_case(people: str, model_family: str, seed: int, half: str, method: str) -> dict:
    import torch

    torch.set_num_threads(1)
    from default_candidates import register_candidate
    from families import landmarked_model
    from statfit.core.threads import flush_denormals_everywhere
    from statfit.registration.job import landmark_alignment
    from statfit.structures.scan import Scan

    flush_denormals_everywhere()
    data = case_data(people, seed, half)
    model = landmarked_model(model_family)
    row = {"people": people, "model": model_family, "seed": seed, "half": half, "method": method}
    seen = data["seen"]
    placed = landmark_alignment(model, data["landmarks"]).apply(model.template)
    held = validation_split(seen.points, placed)
    try:
        result = register_candidate(method, model, Scan(seen.points[~held], seen.normals[~held]),
                                    landmarks=data["landmarks"], threads=1)
    except Exception as exc:   # a refusal is a result too
        return row | {"error": f"{type(exc).__name__}: {exc}".splitlines()[0]}
    return row | {"validation": float(np.nanmean(inside_distance(seen.points[held], result.vertices, model.faces))),
                  "seconds": result.seconds}


def report(rows: list[dict]) -> str:
    full = {(r["people"], r["model"], r["seed"], r["half"], r["method"]): r
            for r in json.loads(FULL_FITS.read_text()) if "held" in r}
    checks = {(r["people"], r["model"], r["seed"], r["half"], r["method"]): r for r in rows if "validation" in r}
    pairs = sorted({(r["people"], r["model"]) for r in rows})
    lines = ["Held-out half (mm, §19's fits of the whole half) of each candidate, of the candidate the "
             "validation quarter chose, and of the better candidate per case (oracle); how often the "
             "choice is the oracle's; the choice ÷ the default, ÷ the landmark-placed mean.", "",
             "| people | model | cases | default | laplacian | chosen | oracle | agrees | chosen ÷ default | "
             "chosen ÷ mean | laplacian chosen |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    totals = {name: [] for name in ("default", "laplacian", "chosen", "oracle", "mean")}
    for people, model in pairs:
        cases = sorted({(s, h) for (p, m, s, h, _) in checks if (p, m) == (people, model)})
        cases = [c for c in cases if all((people, model, *c, k) in checks and (people, model, *c, k) in full
                                         for k in CANDIDATES) and (people, model, *c, "mean") in full]
        if not cases:
            continue
        values = {name: [] for name in totals}
        picked_laplacian = agree = 0
        for case in cases:
            held = {k: full[(people, model, *case, k)]["held"] for k in CANDIDATES}
            chosen = min(CANDIDATES, key=lambda k: checks[(people, model, *case, k)]["validation"])
            oracle = min(CANDIDATES, key=held.get)
            picked_laplacian += chosen == "laplacian"
            agree += chosen == oracle
            for name, value in (("default", held["default"]), ("laplacian", held["laplacian"]),
                                ("chosen", held[chosen]), ("oracle", held[oracle]),
                                ("mean", full[(people, model, *case, "mean")]["held"])):
                values[name].append(value)
        means = {name: float(np.mean(v)) for name, v in values.items()}
        for name, v in values.items():
            totals[name] += v
        lines.append(f"| {people} | {model} | {len(cases)} | {means['default']:.2f} | {means['laplacian']:.2f} | "
                     f"{means['chosen']:.2f} | {means['oracle']:.2f} | {agree}/{len(cases)} | "
                     f"{means['chosen'] / means['default']:.2f} | {means['chosen'] / means['mean']:.2f} | "
                     f"{picked_laplacian}/{len(cases)} |")
    if totals["chosen"]:
        t = {name: float(np.mean(v)) for name, v in totals.items()}
        lines.append(f"| all | all | {len(totals['chosen'])} | {t['default']:.2f} | {t['laplacian']:.2f} | "
                     f"{t['chosen']:.2f} | {t['oracle']:.2f} | | {t['chosen'] / t['default']:.2f} | "
                     f"{t['chosen'] / t['mean']:.2f} | |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--people", type=int, default=2, help="people per family")
    parser.add_argument("--families", nargs="*", default=list(LANDMARKED), help=f"of {', '.join(LANDMARKED)}")
    parser.add_argument("--report", action="store_true", help="only print the tables of the stored rows")
    args = parser.parse_args()
    runs = [(p, m, s, h, method) for p in args.families for m in args.families for s in range(args.people)
            for h in HALVES for method in CANDIDATES]
    run_or_report(fit_case, runs, RESULTS, report, args.report,
                  key=lambda row: (row["people"], row["model"], row["seed"], row["half"], row["method"]))


if __name__ == "__main__":
    main()
