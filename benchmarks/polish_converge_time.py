"""What the last polishes' going on while their objective falls costs (docs/studies.md §48): the pose
search (`estimate_pose`, one torch thread) of realistic one-view scans (4,300 points on the person,
mm, any pose) with §41's rule (SETTLE_MOST 30, no objective test) and as shipped, alternating
``--rounds`` times in one process (:func:`common.alternate`). The scans (``CASES``): a clean scan of
a model's own person, and three of the study's people with clutter (hair, neck and shoulders) or
under another family's model. Prints each search and the ratio of the medians.

    python benchmarks/polish_converge_time.py [--rounds 3]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import warnings
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import alternate, median_ratio  # noqa: E402
from families import build_all, family_model, person  # noqa: E402

# name → (model, people, seed, clutter): a clean scan of a model's own person (stops at 12 steps either
# way), then the study's scans at its 60th, 75th and 90th percentiles of the ratio (docs/studies.md §48)
CASES = {"ICT's person 1 under ICT's head, clean": ("ict", "ict", 1, 0.0),
         "the mask's person 2 under ICT's head, clutter 0.5": ("ict", "ict-mask", 2, 0.5),
         "the embedded head's person 2 under MakeHuman's head, clutter 2": ("makehuman", "embedded", 2, 2.0),
         "MakeHuman's person 2 under MakeHuman's head, clutter 0.5": ("makehuman", "makehuman", 2, 0.5)}
BEFORE = (30, float("inf"))      # (SETTLE_MOST, SETTLE_DROP): §41's rule


def case_scan(name: str):
    """The case's model and realistic scan."""
    from statfit.structures.scan import Scan
    from statfit.synth.scanner import realistic_scan

    model_name, subject, seed, clutter = CASES[name]
    build_all([model_name, subject], seed + 1)
    rng = np.random.default_rng(seed)
    made = realistic_scan(person(subject, seed), family_model(subject).faces, rng, 4300,
                          yaw_deg=rng.uniform(-40, 40), clutter=clutter, units="mm", posed=True)
    return family_model(model_name), Scan.from_mesh(made.vertices, made.faces)


def search(case, rule: tuple[int, float] | None) -> dict:
    """One pose search of the case under ``rule`` (None: as shipped): its seconds."""
    import time

    import statfit.registration.pose.refinement as refinement
    from statfit.registration.pose.search import estimate_pose

    model, scan = case
    shipped = refinement.SETTLE_MOST, refinement.SETTLE_DROP
    refinement.SETTLE_MOST, refinement.SETTLE_DROP = rule or shipped
    try:
        began = time.perf_counter()
        estimate_pose(model, scan, threads=1)
        return {"seconds": time.perf_counter() - began}
    finally:
        refinement.SETTLE_MOST, refinement.SETTLE_DROP = shipped


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    warnings.simplefilter("ignore")
    variants = (BEFORE, None)
    rows = alternate(list(CASES), case_scan, variants, args.rounds, search,
                     lambda rule, row: f"{'before' if rule else 'now'}: {row['seconds']:.3f} s")
    for name in CASES:
        before, now = (statistics.median(row["seconds"] for row in rows[(name, rule)]) for rule in variants)
        print(f"{name}: medians of {args.rounds}, before {before:.2f} s, now {now:.2f} s, "
              f"now ÷ before {median_ratio(rows, name, 'seconds', None, BEFORE):.3f}")


if __name__ == "__main__":
    main()
