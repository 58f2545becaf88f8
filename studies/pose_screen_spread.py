"""The pose search's screen with a tolerance that follows the model's shape spread (docs/studies.md
§44; measured, not shipped).

The search's first step fits the model's mean shape to the scan from 60 rotations and keeps the
poses that lie within TOLERANCE (0.05 of the model's RMS radius) of most points. That tolerance was
chosen on ICT's families, whose modes spread each vertex by 0.080 of the radius; MakeHuman's spread
0.13, and at a MakeHuman face sample's true pose the mean lies within 0.05 of only 61% of its scan.
Here the screen's tolerance is scaled by the model's spread over ICT's (never below 0.05), the rest
of the search as shipped: benchmarks/mask_pose.py's cases (ICT's mask: ×1.03; MakeHuman's face, its
held-out people and its own samples: ×1.61), compared with the shipped rows of
benchmarks/results/mask_pose_cpu.json (the same cases, the same code otherwise).

    python studies/pose_screen_spread.py            # ~6 min on 2 cores
    python studies/pose_screen_spread.py --report
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "pose_screen_spread.json"
SHIPPED = ROOT / "benchmarks" / "results" / "mask_pose_cpu.json"
ICT_SPREAD = 0.080      # ICT's head: the family the screen's tolerance was chosen on
CASES = (("ict-mask", False), ("makehuman-face", False), ("makehuman-face", True))
SEEDS = range(40)
_SHIPPED: dict = {}


def spread(model) -> float:
    """Each vertex's RMS displacement over the modes' spread, over the template's RMS radius."""
    centred = model.template - model.template.mean(axis=0)
    return float(np.sqrt((model.std**2).sum() / model.num_vertices) / np.sqrt((centred**2).sum(axis=1).mean()))


def fit_case(family: str, sampled: bool, seed: int) -> dict:
    import statfit.registration.pose.search as search
    from families import landmarked_model
    from mask_pose import pose_case
    from statfit.model.cut import fitting_model
    from statfit.registration.pose.scoring import TOLERANCE

    factor = max(1.0, spread(fitting_model(landmarked_model(family), "auto", finds_pose=True)) / ICT_SPREAD)
    shipped = _SHIPPED.setdefault("score_poses", search.score_poses)    # a worker runs many cases

    def score_poses(*args, tolerance: float = TOLERANCE, **kwargs):
        return shipped(*args, tolerance=tolerance * factor, **kwargs)

    search.score_poses = score_poses
    row = pose_case(family, seed, "auto", sampled)
    return {"family": family, "sampled": sampled, "factor": factor} | row


def runs() -> list[tuple]:
    from families import build_all

    build_all(["ict", "ict-mask", "makehuman-face"], len(SEEDS))
    return [(family, sampled, seed) for family, sampled in CASES for seed in SEEDS]


def within_share(rows: list[dict]) -> str:
    fitted = [r for r in rows if "without_mm" in r]
    within = sum(r["without_mm"] <= 1.5 * r["placed_mm"] for r in fitted)
    return f"{within} of {len(rows)} within 1.5× ({len(rows) - len(fitted)} refused)"


def shipped_rows(family: str, sampled: bool) -> list[dict]:
    """benchmarks §14's rows of a case, as shipped."""
    stored = json.loads(SHIPPED.read_text())
    return (stored.get("rows") or stored["data"]["rows"])[family + (" samples" if sampled else "")]


def by_case(rows: list[dict]) -> list[tuple[str, str, list[dict], list[dict]]]:
    """Per case measured in ``rows``: who the people are, the model, the shipped rows and ``rows``'."""
    cases = []
    for family, sampled in CASES:
        mine = [r for r in rows if r["family"] == family and r["sampled"] == sampled]
        if mine:
            people = "its own samples" if sampled else ("held-out people" if family == "makehuman-face" else
                                                        "its people")
            cases.append((people, family, shipped_rows(family, sampled), mine))
    return cases


def report(rows: list[dict]) -> str:
    lines = ["| people | model | screen tolerance | shipped | spread-scaled |", "|---|---|---|---|---|"]
    lines += [f"| {people} | {family} | ×{mine[0]['factor']:.2f} | {within_share(before)} | {within_share(mine)} |"
              for people, family, before, mine in by_case(rows)]
    return "\n".join(lines)


if __name__ == "__main__":
    study_main(__doc__, fit_case, runs, RESULTS, report,
               key=lambda row: (row["family"], row["sampled"], row["seed"]))
