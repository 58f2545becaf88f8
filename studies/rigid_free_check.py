"""The rule that fits a model without its modes' rigid motion when that motion is most of what its
modes do (docs/studies.md §44), checked on a family it was not chosen on: MakeHuman's face, the
front of MakeHuman's head model in millimetres (benchmarks/families.py, ``makehuman-face``: a face
mask cut from a body model; 99.9% of its modes' variance is rigid motion). The rule was chosen on
MakeHuman's head (§43).

§19's protocol (studies/cross_family_landmarks.py: one realistic view, split into halves, each half
fitted with its own inner landmarks, the other half held out; mm), the model as built and without its
modes' rigid motion, side by side, on the people of ICT, the mask and MakeHuman's face, 2 people
each, 4 halves; the default, `statistical`, `laplacian` and the landmark-placed mean.

    python studies/rigid_free_check.py            # ~8 min on 2 cores
    python studies/rigid_free_check.py --report
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from rigid_free_modes import FREED, METHODS, SEEDS, fit_case, report  # noqa: E402
from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "rigid_free_check.json"
PEOPLE = ("ict", "ict-mask", "makehuman-face")
MODEL = "makehuman-face"


def runs() -> list[tuple]:
    from families import build_all

    build_all(list(PEOPLE), len(SEEDS))
    return [(p, v, s, h, m) for p in PEOPLE for v in (MODEL, MODEL + FREED) for s in SEEDS
            for h in ("left", "right", "upper", "lower") for m in METHODS]


if __name__ == "__main__":
    study_main(__doc__, fit_case, runs, RESULTS, report,
               key=lambda row: (row["people"], row["model"], row["seed"], row["half"], row["method"]))
