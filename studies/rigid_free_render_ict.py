"""Does `render` fit ICT's head closer without its modes' rigid motion, although that motion is a
fifth of what its modes do (21.3%, under the jobs' 90% rule, docs/studies.md §44)? In `render` the
rigid alignment finds the pose before the fit and the fit cannot turn the model, so modes that move
the head only trade with that pose: ICT's mask (29.5%) fitted its own people 5.5× closer without
them (§43, each person placed on the true pose). ICT's head is the family the render defaults were chosen on.

§18's protocol (studies/cross_family_render.py: a person in one normal map at 256², the default
rigid alignment, each method at its tuned settings; distance of the person's surface points to the
fit, % of their RMS radius), ICT's head as built and without its modes' rigid motion, side by side,
on the people of ICT, the mask and MakeHuman, 2 each. The person is misplaced by MISPLACED (degrees
turned, % of their radius moved; the fit must find the pose; every method) and also placed as §18
places them (on the model's mean: the fit starts on the true pose; the default and `laplacian`):
modes without rigid motion cannot move a fit off a pose it starts on, which only the second
placement rewards.

    python studies/rigid_free_render_ict.py            # ~35 min on 2 cores
    python studies/rigid_free_render_ict.py --report
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from rigid_free_modes import FREED  # noqa: E402
from rigid_free_render import MISPLACED, PEOPLE, SEEDS, SIZE, fit_case, placement_report  # noqa: E402
from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "rigid_free_render_ict.json"
MODEL = "ict"
# the default and `laplacian` (the pair the default most often loses to) first: a stopped run has them
METHODS = ("default", "laplacian", "statistical", "hybrid", "pca")


def runs() -> list[tuple]:
    from families import build_all

    build_all(list(PEOPLE), len(SEEDS))
    return [(p, v, s, m, SIZE, misplaced) for misplaced in (MISPLACED, 0.0)
            for m in (METHODS if misplaced else METHODS[:2]) for p in PEOPLE for v in (MODEL, MODEL + FREED)
            for s in SEEDS]


if __name__ == "__main__":
    study_main(__doc__, fit_case, runs, RESULTS, placement_report,
               key=lambda row: (row["people"], row["model"], row["seed"], row["method"], row["size"],
                                row.get("misplaced", 0.0)))
