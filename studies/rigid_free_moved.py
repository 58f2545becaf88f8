"""`render` drops a model's modes' rigid motion where its alignment moved the model off the place
those modes give its people (docs/studies.md §46).

§45 found that a model below the jobs' 90% rule (ICT's head, 21%; its face mask, 30%) fits other
people closer without its modes' rigid motion when the fit must find the pose, and its own people,
placed where its statistics place them, worse (the depth those statistics predict; one view cannot
find it). The alignment tells the two apart: it leaves ICT's own §5 people where they are and moves
the misplaced ones far (`statfit.model.cut.rigid_motion_distance`: 0 against 9–33 standard
deviations of the modes' rigid motion). So `--rigid-modes auto` now fits a model at most 50% rigid
(`PLACE_DECIDES`: not MakeHuman's body model, whose size goes with its place) without that motion
where the alignment moved it more than `OFF_ITS_PLACE` (4.1, the 99th percentile of that distance
for a move drawn from the modes' own spread; chosen from the statistics, not from these rows).

Side by side in one run, each case with `--rigid-modes keep` (as built) and `auto` (the rule):
§18's protocol (studies/cross_family_render.py, 256², every method) with ICT's head and its face
mask on the people of ICT, the mask and MakeHuman, 2 each, misplaced by MISPLACED (the fit must find
the pose) and placed as §18 places them (every method since session 43). §5's four in-family cases
at 512² are checked for what the rule decides (its distance; the fit is unchanged where it does not
fire). The misplaced `keep` rows are the same bits as studies/cross_family_render.py's misplaced
rows (49 compared); the rest of them were taken from there (``copied``).

    python studies/rigid_free_moved.py            # ~2 h on 2 cores (244 fits)
    python studies/rigid_free_moved.py --report
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from rigid_free_render import MISPLACED, PEOPLE, SEEDS, SIZE  # noqa: E402
from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "rigid_free_moved.json"
MODELS = ("ict", "ict-mask")
RULES = ("keep", "auto")
# the default and `laplacian` (the pair the default most often loses to) first: a stopped run has them
METHODS = ("default", "laplacian", "statistical", "hybrid", "pca")


def fit_case(kind: str, people: str, model: str, seed: int, method: str, rule: str) -> dict:
    import torch

    torch.set_num_threads(1)
    row = {"kind": kind, "people": people, "model": model, "seed": seed, "method": method, "rule": rule}
    if kind == "in-family":
        return row | in_family_distance(people)
    from cross_family_render import fit_case as fit_view

    misplaced = MISPLACED if kind == "misplaced" else 0.0
    return fit_view(people, model, seed, method, SIZE, misplaced, rigid_modes=rule) | row


def in_family_distance(case_name: str) -> dict:
    """How far the default's alignment moves ICT's head off its place on §5's case ``case_name``
    (512²), and whether the rule fires."""
    import torch

    from common import ICT
    from families import family_model
    from statfit.render.job import PosedView
    from study_render import CASES, make_target

    model = family_model("ict")
    case = next(c for c in CASES if c.name == case_name)
    _, camera, normal_map = make_target(model, ICT / "ict_face_expressions.npz", case, 512)
    view = PosedView.of(model, normal_map, camera, torch.device("cpu"), torch.float32)
    distance = view.moved_by(model)
    from statfit.model.cut import OFF_ITS_PLACE

    return {"distance": distance, "rigid_free": distance > OFF_ITS_PLACE}


def runs() -> list[tuple]:
    from families import build_all
    from study_render import CASES

    build_all(list(PEOPLE), len(SEEDS))
    return ([("in-family", c.name, "ict", 0, "default", "auto") for c in CASES]
            + [(kind, p, m, s, method, rule) for kind in ("misplaced", "placed")
               for method in METHODS for m in MODELS for p in PEOPLE for s in SEEDS for rule in RULES])


def report(rows: list[dict]) -> str:
    from cross_family_render import report as view_report

    parts = []
    inside = [r for r in rows if r["kind"] == "in-family"]
    if inside:
        parts.append("**ICT in family (§5, 512²)**: the alignment's move, standard deviations of the modes' rigid "
                     "motion: " + ", ".join(f"{r['people']} {r['distance']:.2f}"
                                            + (" (fires)" if r["rigid_free"] else "") for r in inside))
    for kind in ("misplaced", "placed"):
        chosen = [r | {"model": f"{r['model']}, {r['rule']}"} for r in rows if r["kind"] == kind]
        if not chosen:
            continue
        fired = [r for r in chosen if r["rule"] == "auto" and "all" in r]
        share = f"{sum(r['rigid_free'] for r in fired)} of {len(fired)}"
        table = view_report(chosen) + "\n\n" if any(r["method"] != "default" for r in chosen) else ""
        parts.append(f"**{kind.capitalize()}** (the rule fired on {share} fits)\n\n" + table + _per_case(rows, kind))
    return "\n\n".join(parts)


def _per_case(rows: list[dict], kind: str) -> str:
    """The default's error per case, as built → the rule, and their ratio."""
    by = {(r["people"], r["model"], r["seed"], r["rule"]): r for r in rows
          if r["kind"] == kind and r["method"] == "default" and "all" in r}
    cells = []
    for (people, model, seed, rule), r in by.items():
        if rule == "keep" and (people, model, seed, "auto") in by:
            after = by[(people, model, seed, "auto")]
            cells.append(f"{people} {seed} → {model}: {r['all']:.2f} → {after['all']:.2f} "
                         f"({after['all'] / r['all']:.2f}×{', fired' if after['rigid_free'] else ''})")
    ratios = [by[(p, m, s, "auto")]["all"] / by[(p, m, s, "keep")]["all"] for (p, m, s, rule) in by
              if rule == "keep" and (p, m, s, "auto") in by]
    summary = f"geometric mean {np.exp(np.mean(np.log(ratios))):.3f}×" if ratios else ""
    return "Default per case, as built → the rule: " + "; ".join(cells) + f". {summary}"


if __name__ == "__main__":
    study_main(__doc__, fit_case, runs, RESULTS, report,
               key=lambda row: (row["kind"], row["people"], row["model"], row["seed"], row["method"], row["rule"]))
