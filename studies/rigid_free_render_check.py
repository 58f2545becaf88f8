"""The rule that fits a model without its modes' rigid motion when that motion is most of what its
modes do (docs/studies.md §44), checked in `render` on a family it was not chosen on: MakeHuman's
face (benchmarks/families.py, ``makehuman-face``; 99.9% rigid). The rule was chosen on MakeHuman's
head (§43).

§18's protocol (studies/cross_family_render.py: a person in one normal map at 256², the default
rigid alignment, each method at its tuned settings; distance of the person's surface points to the
fit, % of their RMS radius), the model as built and without its modes' rigid motion, side by side, on
the people of ICT, the mask and MakeHuman's face, 2 each; the default and `laplacian`. The person
is placed as §18 places them (on the model's mean: the fit starts on the true pose) and also
misplaced by MISPLACED (degrees turned, % of their radius moved), so the fit must find the pose:
modes without rigid motion cannot move a fit off a pose it starts on, which only the first
placement rewards.

    python studies/rigid_free_render_check.py            # ~20 min on 2 cores
    python studies/rigid_free_render_check.py --report
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from rigid_free_check import MODEL, PEOPLE  # noqa: E402
from rigid_free_modes import FREED  # noqa: E402
from rigid_free_render import MISPLACED, SEEDS, SIZE, fit_case, placement_report  # noqa: E402
from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "rigid_free_render_check.json"
METHODS = ("default", "laplacian")


def runs() -> list[tuple]:
    from families import build_all

    build_all(list(PEOPLE), len(SEEDS))
    return [(p, v, s, m, SIZE, misplaced) for misplaced in (0.0, MISPLACED) for p in PEOPLE
            for v in (MODEL, MODEL + FREED) for s in SEEDS for m in METHODS]


if __name__ == "__main__":
    study_main(__doc__, fit_case, runs, RESULTS, placement_report,
               key=lambda row: (row["people"], row["model"], row["seed"], row["method"], row["size"],
                                row.get("misplaced", 0.0)))
