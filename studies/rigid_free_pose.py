"""The landmark-free pose of a face mask cut from a body model, with its modes as built and without
their rigid motion (docs/studies.md §44): benchmarks/mask_pose.py's cases (a realistic scan of a
person of the family in any rotation, offset and unit, yaw within ±45°, fitted by ``pca`` without
landmarks and with its 51 inner landmarks placing the start only) on the MakeHuman face family
(benchmarks/families.py, ``makehuman-face``; 99.9% rigid), ``--rigid-modes keep`` against ``auto``
(which drops the motion), side by side.

    python studies/rigid_free_pose.py            # ~4 min on 2 cores
    python studies/rigid_free_pose.py --report
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "rigid_free_pose.json"
FAMILY, SEEDS, RULES = "makehuman-face", range(12), ("keep", "auto")


def fit_case(seed: int, rule: str) -> dict:
    from mask_pose import pose_case

    return {"rule": rule} | pose_case(FAMILY, seed, rule)


def runs() -> list[tuple]:
    from families import build_all

    build_all([FAMILY], len(SEEDS))
    return [(seed, rule) for seed in SEEDS for rule in RULES]


def report(rows: list[dict]) -> str:
    lines = ["| modes | scans | refused without landmarks | fitted within 1.5× of the landmark-placed fit | "
             "landmark error without (mm, fitted) | with landmarks placing the start (mm, all) |", "|---|---|---|---|---|---|"]
    for rule in RULES:
        mine = [r for r in rows if r["rule"] == rule]
        fitted = [r for r in mine if "without_mm" in r]
        within = sum(r["without_mm"] <= 1.5 * r["placed_mm"] for r in fitted)
        name = "as built (`keep`)" if rule == "keep" else "without rigid motion (`auto`)"
        lines.append(f"| {name} | {len(mine)} | {len(mine) - len(fitted)} | {within} | "
                     + (f"{np.mean([r['without_mm'] for r in fitted]):.2f}" if fitted else "–")
                     + f" | {np.mean([r['placed_mm'] for r in mine]):.2f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    study_main(__doc__, fit_case, runs, RESULTS, report, key=lambda row: (row["seed"], row["rule"]))
