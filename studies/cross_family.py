"""Cross-family registration: people of one model family scanned, fitted with another family's model
(issue 37; docs/studies.md §17). A MakeHuman person fitted with ICT is a far better stand-in for a
real person than ICT's own modes: another population, topology and resolution.

Families and people: benchmarks/families.py (ICT head, ICT face mask, MakeHuman head, embedded
head). Each person is scanned as a range scanner would (statfit.synth.scanner: one view, yaw in
±30°, any rotation, millimetres, no clutter), the scan split at its middle into a left and a right
half in the person's own frame; each half is fitted alone with the pose found without landmarks, and
the other half is the test:

- ``held``: mean distance (mm) from the held-out half's scan points to the fitted surface, leaving
  out the points whose nearest surface point is on the fit's open boundary (beyond what the model
  covers: a mask cannot be asked about the back of a head);
- ``seen``: the same for the fitted half's points.

"mean" is the model's mean placed by the pose search register runs (no shape fitted): the bar every fit must
beat. Distances need no vertex correspondence, so any model can be scored on any person.

    python studies/cross_family.py --people 2          # all pairs; cases run two at a time
    python studies/cross_family.py --report            # tables from studies/results/cross_family.json
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from families import FAMILIES  # noqa: E402
from study_runs import run_or_report  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "cross_family.json"
METHODS = ("mean", "default", "pca", "statistical", "hybrid", "laplacian")
SINGLE_METHODS = METHODS[2:]
HALVES = ("left", "right")
SCAN_POINTS = 4300


def case_scan(people: str, seed: int):
    """The person's realistic scan (mm, posed) and the person → scan similarity."""
    from families import family_model, person
    from statfit.structures.scan import Scan
    from statfit.synth.scanner import realistic_scan

    shape = person(people, seed)
    faces = family_model(people).faces
    rng = np.random.default_rng(500 + seed)
    made = realistic_scan(shape, faces, rng, points=SCAN_POINTS, yaw_deg=rng.uniform(-30, 30), clutter=0.0,
                          holes=0, units="mm")
    return Scan.from_mesh(made.vertices, made.faces), made.transform


def inside_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Distances (M,) from ``points`` (M, 3) to the surface, NaN beyond its open boundary
    (:func:`statfit.geometry.metrics.inside_distance`, which the register fallback also uses)."""
    from statfit.geometry.metrics import inside_distance as library_inside_distance

    return library_inside_distance(points, vertices, faces)


def fit_case(people: str, model_family: str, seed: int, half: str, method: str) -> dict:
    import torch

    torch.set_num_threads(1)
    from families import family_model
    from statfit.core.threads import flush_denormals_everywhere
    from default_candidates import register_candidate
    from statfit.model.cut import fitting_model
    from statfit.registration.pose.search import estimate_pose
    from statfit.structures.scan import Scan

    flush_denormals_everywhere()
    scan, transform = case_scan(people, seed)
    own = transform.inverse_apply(scan.points)
    middle = np.median(own[:, 0])
    seen = (own[:, 0] > middle) if half == "left" else (own[:, 0] <= middle)
    fitted_half = Scan(scan.points[seen], scan.normals[seen])
    model = family_model(model_family)
    row = {"people": people, "model": model_family, "seed": seed, "half": half, "method": method}
    try:
        if method == "mean":    # posed as register poses it: by the model it fits (without its modes' rigid motion
            posed = fitting_model(model)    # where that is most of them, §44), or the pose leaves it to the modes
            vertices, seconds, fallback = estimate_pose(posed, fitted_half).transform.apply(model.template), 0.0, None
        else:
            result = register_candidate(method, model, fitted_half, threads=1)
            vertices, seconds, fallback = result.vertices, result.seconds, result.fallback
    except Exception as exc:   # a refusal is a result too
        return row | {"error": f"{type(exc).__name__}: {exc}".splitlines()[0]}
    held = inside_distance(scan.points[~seen], vertices, model.faces)
    seen_distance = inside_distance(scan.points[seen], vertices, model.faces)
    return row | {"held": float(np.nanmean(held)), "held_covered": float(np.mean(~np.isnan(held))),
                  "seen": float(np.nanmean(seen_distance)), "seconds": seconds} | ({"fallback": fallback} if fallback else {})


def index_rows(rows: list[dict]) -> tuple[dict, list[tuple[str, str]], list[str]]:
    """Rows by (people, model, seed, half, method); the (people, model) pairs and the methods, in
    the order of METHODS, then any others (candidates) in the order they came."""
    by = {(r["people"], r["model"], r["seed"], r["half"], r["method"]): r for r in rows}
    pairs = list(dict.fromkeys((r["people"], r["model"]) for r in rows))
    present = dict.fromkeys(r["method"] for r in rows)
    return by, pairs, [m for m in METHODS if m in present] + [m for m in present if m not in METHODS]


def fitted_cases(by: dict, people: str, model: str, methods: list[str]) -> tuple[list[tuple], list[tuple]]:
    """The pair's (seed, half) cases, and those every method fitted (scored)."""
    cases = sorted({(s, h) for (p, m, s, h, _) in by if (p, m) == (people, model)})
    return cases, [c for c in cases if all("held" in by.get((people, model, *c, m), {}) for m in methods)]


def report(rows: list[dict]) -> str:
    by, pairs, methods = index_rows(rows)
    lines = ["Held-out half: mean distance (mm) of the held-out half's scan points to the fit, over the "
             "cases (people × halves) every method fitted; the default's worst case ÷ the mean's on the "
             "same case in brackets; refused: cases the pose search refused (for every method).", "",
             "| people | model | cases | refused | " + " | ".join(methods)
             + " | default ÷ mean | default ÷ best method | covered |",
             "|---|---|---|---|" + "---|" * (len(methods) + 3)]
    for people, model in pairs:
        cases, fitted = fitted_cases(by, people, model, methods)
        if not fitted:
            lines.append(f"| {people} | {model} | 0 | {len(cases)} |" + " – |" * (len(methods) + 3))
            continue
        means = {m: float(np.mean([by[(people, model, *c, m)]["held"] for c in fitted])) for m in methods}
        ratios = [by[(people, model, *c, "default")]["held"] / by[(people, model, *c, "mean")]["held"] for c in fitted]
        best = min(v for m, v in means.items() if m in SINGLE_METHODS)
        covered = np.mean([by[(people, model, *c, "default")]["held_covered"] for c in fitted])
        lines.append(f"| {people} | {model} | {len(fitted)} | {len(cases) - len(fitted)} | "
                     + " | ".join(f"{means[m]:.2f}" for m in methods)
                     + f" | {means['default'] / means['mean']:.2f} (worst {max(ratios):.2f}) | "
                     f"{means['default'] / best:.2f} | {covered:.0%} |")
    errors = [r for r in rows if "error" in r and r["method"] == "default"]
    if errors:
        lines += ["", "Refused: " + "; ".join(f"{r['people']} {r['seed']} {r['half']} → {r['model']}: "
                                              f"{r['error'].split(': ', 1)[-1][:110]}" for r in errors)]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--people", type=int, default=2, help="people per family")
    parser.add_argument("--families", nargs="*", default=list(FAMILIES[:3]), help=f"of {', '.join(FAMILIES)}")
    parser.add_argument("--methods", nargs="*", default=list(METHODS),
                        help="methods, pipelines or candidates (studies/default_candidates.py) to run and report")
    parser.add_argument("--report", action="store_true", help="only print the tables of the stored rows")
    args = parser.parse_args()
    runs = [(p, m, s, h, method) for p in args.families for m in args.families for s in range(args.people)
            for h in HALVES for method in args.methods]
    if not args.report:
        from families import build_all

        build_all(args.families, args.people)
    run_or_report(fit_case, runs, RESULTS, lambda rows: report([r for r in rows if r["method"] in (*METHODS, *args.methods)]),
                  args.report,
                  key=lambda row: (row["people"], row["model"], row["seed"], row["half"], row["method"]))


if __name__ == "__main__":
    main()
