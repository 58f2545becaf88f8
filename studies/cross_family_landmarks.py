"""Cross-family registration with landmarks: what a fit guesses in the half of a face it did not see,
for a person of another model family (issue 37, part 2; docs/studies.md §19).

The protocol of §15 (studies/held_out_half.py) on the cross-family cases of §17
(studies/cross_family.py): people of the ICT head, ICT face-mask and MakeHuman head families
(benchmarks/families.py, with their 68 landmarks) are scanned as a range scanner would (one view, yaw
within ±30°, any rotation, millimetres, no clutter, 4,300 points) and fitted with each family's
model. The scan is split at the inner landmarks' centroid, in the person's own frame, into halves:
left / right and upper / lower. Each half is fitted alone with the inner landmarks (Multi-PIE 17–67,
1 mm noise) of that half only; the other half is the test:

- ``held``: mean distance (mm) from the held-out half's scan points to the fitted surface, leaving
  out points whose nearest surface point is on the fit's open boundary (beyond what the model covers);
- ``held_lm``: mean distance (mm) of the held-out half's landmark vertices from the person's true
  landmarks;
- ``seen``: the mean distance of the fitted half's points.

"mean" is the model's mean placed by the landmark similarity (no shape fitted): the bar every fit
must beat. Every method at its tuned settings; one thread per fit.

    python studies/cross_family_landmarks.py --people 2      # ~25 min on 2 cores
    python studies/cross_family_landmarks.py --report        # tables from the stored rows
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from cross_family import (METHODS, SINGLE_METHODS, case_scan, fitted_cases, index_rows,  # noqa: E402
                          inside_distance)
from families import LANDMARKED  # noqa: E402
from study_runs import run_or_report  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "cross_family_landmarks.json"
HALVES = ("left", "right", "upper", "lower")
INNER = slice(17, 68)
NOISE_MM = 1.0


def case_data(people: str, seed: int, half: str) -> dict:
    """The fitted half (scan points, landmarks with NaN rows for those not given) and the test: the
    held-out half's points, the true landmarks (68, 3) and which of them are held out; in the scan's
    frame (mm)."""
    from families import person_landmarks
    from statfit.structures.scan import Scan

    scan, transform = case_scan(people, seed)
    own = transform.inverse_apply(scan.points)
    own_landmarks = person_landmarks(people, seed)
    truth = transform.apply(own_landmarks)
    inner = np.zeros(len(truth), dtype=bool)
    inner[INNER] = True
    centre = own_landmarks[inner].mean(axis=0)
    axis, sign = {"left": (0, 1), "right": (0, -1), "upper": (1, 1), "lower": (1, -1)}[half]
    seen_points = sign * (own[:, axis] - centre[axis]) > 0
    seen_landmarks = inner & (sign * (own_landmarks[:, axis] - centre[axis]) > 0)
    noisy = truth + np.random.default_rng(900 + seed).normal(scale=NOISE_MM, size=truth.shape)
    return {"seen": Scan(scan.points[seen_points], scan.normals[seen_points]), "held": scan.points[~seen_points],
            "landmarks": np.where(seen_landmarks[:, None], noisy, np.nan), "truth": truth,
            "held_landmarks": inner & ~seen_landmarks}


def fit_case(people: str, model_family: str, seed: int, half: str, method: str) -> dict:
    import torch

    torch.set_num_threads(1)
    from families import landmarked_model
    from statfit.core.threads import flush_denormals_everywhere
    from default_candidates import register_candidate
    from statfit.registration.prealign import landmark_alignment

    flush_denormals_everywhere()
    data = case_data(people, seed, half)
    model = landmarked_model(model_family)
    row = {"people": people, "model": model_family, "seed": seed, "half": half, "method": method}
    try:
        if method == "mean":
            vertices, seconds, fallback = landmark_alignment(model, data["landmarks"]).apply(model.template), 0.0, None
        else:
            result = register_candidate(method, model, data["seen"], landmarks=data["landmarks"], threads=1)
            vertices, seconds, fallback = result.vertices, result.seconds, result.fallback
    except Exception as exc:   # a refusal is a result too
        return row | {"error": f"{type(exc).__name__}: {exc}".splitlines()[0]}
    held = inside_distance(data["held"], vertices, model.faces)
    held_lm = data["held_landmarks"]
    return row | {"held": float(np.nanmean(held)), "held_covered": float(np.mean(~np.isnan(held))),
                  "seen": float(np.nanmean(inside_distance(data["seen"].points, vertices, model.faces))),
                  "held_lm": float(np.linalg.norm(vertices[model.landmarks[held_lm]] - data["truth"][held_lm],
                                                  axis=1).mean()),
                  "seconds": seconds} | ({"fallback": fallback} if fallback else {})


def report(rows: list[dict]) -> str:
    by, pairs, methods = index_rows(rows)
    others = [m for m in methods if m in SINGLE_METHODS]
    lines = ["Held-out half with the fitted half's landmarks: mean distance (mm) of the held-out half's scan "
             "points to the fit, over the cases (people × 4 halves) every method fitted; then the default "
             "÷ the mean's (worst case), ÷ the best single method's, and the held-out landmarks' error (mm).", "",
             "| people | model | cases | " + " | ".join(methods)
             + " | default ÷ mean (worst) | default ÷ best | landmarks: mean | default | best method | covered |",
             "|---|---|---|" + "---|" * (len(methods) + 6)]
    for people, model in pairs:
        _, fitted = fitted_cases(by, people, model, methods)
        if not fitted:
            lines.append(f"| {people} | {model} | 0 |" + " – |" * (len(methods) + 6))
            continue

        def mean(method: str, key: str = "held") -> float:
            return float(np.mean([by[(people, model, *c, method)][key] for c in fitted]))

        ratios = [by[(people, model, *c, "default")]["held"] / by[(people, model, *c, "mean")]["held"] for c in fitted]
        best = min(others, key=mean)
        best_lm = min(mean(m, "held_lm") for m in others)
        covered = np.mean([by[(people, model, *c, "default")]["held_covered"] for c in fitted])
        lines.append(f"| {people} | {model} | {len(fitted)} | " + " | ".join(f"{mean(m):.2f}" for m in methods)
                     + f" | {mean('default') / mean('mean'):.2f} ({max(ratios):.2f}) | "
                     f"{mean('default') / mean(best):.2f} ({best}) | {mean('mean', 'held_lm'):.2f} | "
                     f"{mean('default', 'held_lm'):.2f} | {best_lm:.2f} | {covered:.0%} |")
    halves = [h for h in HALVES if any(r["half"] == h for r in rows)]
    lines += ["", "By the half fitted (all pairs): mean held-out distance (mm).", "",
              "| half | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for half in halves:
        cases = {(p, m, s) for (p, m, s, h, _) in by if h == half}
        fitted = [c for c in cases if all("held" in by.get((*c, half, m), {}) for m in methods)]
        lines.append(f"| {half} | " + " | ".join(f"{np.mean([by[(*c, half, m)]['held'] for c in fitted]):.2f}"
                                              for m in methods) + " |")
    errors = [r for r in rows if "error" in r]
    if errors:
        lines += ["", "Refused: " + "; ".join(f"{r['method']} {r['people']} {r['seed']} {r['half']} → {r['model']}: "
                                              f"{r['error'].split(': ', 1)[-1][:110]}" for r in errors)]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--people", type=int, default=2, help="people per family")
    parser.add_argument("--families", nargs="*", default=list(LANDMARKED), help=f"of {', '.join(LANDMARKED)}")
    parser.add_argument("--methods", nargs="*", default=list(METHODS),
                        help="methods, pipelines or candidates (studies/default_candidates.py) to run and report")
    parser.add_argument("--report", action="store_true", help="only print the tables of the stored rows")
    parser.add_argument("--results", type=Path, default=RESULTS, help="the rows' JSON file")
    args = parser.parse_args()
    runs = [(p, m, s, h, method) for p in args.families for m in args.families for s in range(args.people)
            for h in HALVES for method in args.methods]
    if not args.report:
        from families import build_all, landmarked_model

        build_all(args.families, args.people)
        for family in args.families:
            landmarked_model(family)
    run_or_report(fit_case, runs, args.results, lambda rows: report([r for r in rows if r["method"] in (*METHODS, *args.methods)]),
                  args.report,
                  key=lambda row: (row["people"], row["model"], row["seed"], row["half"], row["method"]))


if __name__ == "__main__":
    main()
