"""A model's modes without rigid motion, in `render` (docs/studies.md §43): §18's cross-family
protocol (studies/cross_family_render.py: a person of one family in one normal map at 256², fitted
with a family's model by each method at its tuned settings, the default rigid alignment; distance of
the person's surface points to the fit, % of their RMS radius) with MakeHuman's head model and ICT's
face mask, each as built and without its modes' rigid motion, side by side, on the people of ICT,
the mask and MakeHuman, 2 each.

    python studies/rigid_free_render.py            # ~40 min on 2 cores
    python studies/rigid_free_render.py --report
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from rigid_free_modes import VARIANTS, use_variants  # noqa: E402
from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "rigid_free_render.json"
PEOPLE = ("ict", "ict-mask", "makehuman")
SEEDS = (0, 1)
SIZE = 256


def fit_case(people: str, variant: str, seed: int, method: str, size: int, misplaced: float = 0.0) -> dict:
    use_variants()
    from cross_family_render import fit_case as fit_view

    return fit_view(people, variant, seed, method, size, misplaced)


def runs() -> list[tuple]:
    from cross_family_render import METHODS
    from families import build_all

    build_all(list(PEOPLE), len(SEEDS))
    return [(p, v, s, m, SIZE) for p in PEOPLE for v in VARIANTS for s in SEEDS for m in METHODS]


def report(rows: list[dict]) -> str:
    from cross_family_render import report as view_report

    return view_report(rows)


MISPLACED = 5.0     # degrees turned and % of the radius moved, where a study also misplaces the person


def placement_report(rows: list[dict]) -> str:
    """:func:`report`'s tables, one for the people misplaced by MISPLACED (the fit must find the
    pose) and one for those placed on the model's mean (§18: the fit starts on the true pose)."""
    return "\n\n".join(f"**{title}**\n\n" + report([r for r in rows if r.get("misplaced", 0.0) == misplaced])
                       for misplaced, title in ((MISPLACED, f"Misplaced by {MISPLACED:g}° and {MISPLACED:g}%"),
                                                (0.0, "Placed on the model's mean (§18)"))
                       if any(r.get("misplaced", 0.0) == misplaced for r in rows))


if __name__ == "__main__":
    study_main(__doc__, fit_case, runs, RESULTS, report,
               key=lambda row: (row["people"], row["model"], row["seed"], row["method"], row["size"]))
