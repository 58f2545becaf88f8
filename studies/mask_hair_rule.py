"""The head's hair rule on a face mask: does it mend §34's fringe, and what does it cost a person of
another family (issue 37, part 1; docs/studies.md §36; measured, not shipped).

A face-mask model's ``face`` region covers the whole mask, so register's hair rule
(:mod:`statfit.registration.hair`) finds nothing off the face to call hair, and a fringe over the
forehead is fitted as forehead (§34: 2.1–3.0 mm for every method). Where the mask has landmarks, the
head's own definitions can stand in (:func:`statfit.model.statmodel.face_triangles` and
:func:`~statfit.model.statmodel.scalp_triangles` of the model without its ``face`` region):

- ``landmarks' face``: the face-only fit's face is the triangles within 0.5 radii of a landmark, and
  points lying 0.05 radii outside that fit beyond it are hair;
- ``and a scalp``: also every point nearest the triangles 0.15 radii above the highest landmark,
  wherever it lies (the head's rule under clutter, §16).

The rule runs only where the pose search finds clutter. Scored on the ICT mask (the only mask here
with landmarks): §34's realistic scans of its own people (four kinds of clutter × three people; mean
vertex error, mm) and §17's half scans of the four families fitted with it, without landmarks (held-out
distance, mm; clean scans, where a person of another family can look like clutter). The register
default as shipped, its fallback on.

    python studies/mask_hair_rule.py            # 84 fits, two at a time; ~2 min on 2 cores
    python studies/mask_hair_rule.py --report   # the tables from studies/results/mask_hair_rule.json
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from study_runs import study_main  # noqa: E402

ROWS = ROOT / "studies" / "results" / "mask_hair_rule.json"
MASK = "ICT face mask (3,000 vertices, mm)"
RULES = ("shipped (no hair on a mask)", "landmarks' face", "landmarks' face and a scalp")
SCANS = ("no clutter", "hair", "neck", "hair and neck")


def use_rule(rule: str) -> None:
    """Set register's hair rule (statfit.registration.posed's face and scalp) to ``rule`` (module
    docstring)."""
    import dataclasses

    import statfit.registration.posed as posed
    from statfit.model import statmodel

    if rule == RULES[0]:        # a worker runs many cases: undo an earlier case's patch
        posed.face_triangles, posed.scalp_triangles = statmodel.face_triangles, statmodel.scalp_triangles
        return

    def without_mask_face(model):
        whole = model.regions and "face" in model.regions and statmodel.region_triangles(model, "face").all()
        if not whole or model.landmarks is None:
            return model
        return dataclasses.replace(model, regions={k: v for k, v in model.regions.items() if k != "face"})

    posed.face_triangles = lambda model, *radius: statmodel.face_triangles(without_mask_face(model), *radius)
    if rule == RULES[2]:
        posed.scalp_triangles = lambda model: statmodel.scalp_triangles(without_mask_face(model))
    else:
        posed.scalp_triangles = lambda model: np.zeros(len(model.faces), dtype=bool)


def run_case(rule: str, name: str, *key) -> dict:
    import torch

    torch.set_num_threads(1)
    use_rule(rule)
    if name == "§34":
        import mask_clutter

        mask_clutter.FITS = {"default": ("default", True)}
        row = mask_clutter.run_case(MASK, *key)
        return {"rule": rule, "set": name, "case": list(key), "error": row["default mm"]}
    import default_fallback

    row = default_fallback.run_case(name, *key)
    return {"rule": rule, "set": name, "case": list(key), "error": row.get("held"), "refused": row.get("error")}


def runs() -> list[tuple]:
    import default_fallback

    cases = [("§34", scan, seed) for scan in SCANS for seed in range(3)]
    cases += [run for run in default_fallback.runs() if run[0] == "§17" and run[2] == "ict-mask"]
    return [(rule, *case) for case in cases for rule in RULES]


def row_key(row: dict) -> tuple:
    return (row["rule"], row["set"], *row["case"])


def report(rows: list[dict]) -> str:
    groups = {f"§34 {scan}": lambda r, s=scan: r["set"] == "§34" and r["case"][0] == s for scan in SCANS}
    people = dict.fromkeys(r["case"][0] for r in rows if r["set"] == "§17")
    groups |= {f"§17 {p} people": lambda r, p=p: r["set"] == "§17" and r["case"][0] == p for p in people}
    groups["§17 all"] = lambda r: r["set"] == "§17"
    lines = ["Mean error (mm) with the ICT mask, each rule; cases in brackets.", "",
             "| cases | " + " | ".join(RULES) + " |", "|---|" + "---|" * len(RULES)]
    for label, chosen in groups.items():
        cells = []
        for rule in RULES:
            errors = [r["error"] for r in rows if r["rule"] == rule and chosen(r) and r["error"] is not None]
            cells.append(f"{np.mean(errors):.3f} ({len(errors)})" if errors else "–")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    study_main(__doc__, run_case, runs, ROWS, report, row_key)


if __name__ == "__main__":
    main()
