"""`register_many`'s host work side by side: each fit's pose search, closed-form stage and fallback
test on threads beside the others' (as shipped) against one after another (as before, the gradient
stages stepped together either way), alternating in one process. Scans: realistic scans of ICT's
people (benchmarks/families.py; one view, yaw within ±40°, any pose, mm, 4,300 points, clutter 0.5),
the default, torch's threads as the fit chooses them. Prints seconds for the batch and whether both
give the same vertices; then the ratio of medians.

    python benchmarks/many_side_by_side.py [--scans 8] [--rounds 2]
"""
from __future__ import annotations

import argparse
import time
import warnings
from contextlib import nullcontext
from unittest import mock

import numpy as np

from common import alternate, median_ratio

VARIANTS = ("one after another", "side by side")


def scans_of(count: int) -> list:
    from families import family_model, person

    from statfit.structures.scan import Scan
    from statfit.synth.scanner import realistic_scan

    scans = []
    for seed in range(count):
        rng = np.random.default_rng(seed)
        made = realistic_scan(person("ict", seed), family_model("ict").faces, rng, yaw_deg=rng.uniform(-40, 40),
                              clutter=0.5, units="mm", posed=True)
        scans.append(Scan.from_mesh(made.vertices, made.faces))
    return scans


def fit(scans: list, variant: str) -> dict:
    from families import family_model

    from statfit.registration import many

    one_at_a_time = mock.patch.object(many, "task_threads", lambda tasks, cap=None: 1)
    with warnings.catch_warnings(), (one_at_a_time if variant == VARIANTS[0] else nullcontext()):
        warnings.simplefilter("ignore")
        started = time.perf_counter()
        outcomes = many.register_many(family_model("ict"), scans)
        seconds = time.perf_counter() - started
    return {"seconds": seconds, "vertices": [o.fit.vertices for o in outcomes if o.fit is not None]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scans", type=int, default=8)
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args()
    name = f"{args.scans} ICT scans"
    rows = alternate([name], lambda _: scans_of(args.scans), VARIANTS, args.rounds, fit,
                     lambda variant, row: f"{variant}: {row['seconds']:.2f} s, {args.scans / row['seconds']:.3f} fits/s")
    first, second = (rows[(name, variant)][0]["vertices"] for variant in VARIANTS)
    same = len(first) == len(second) and all(np.array_equal(a, b) for a, b in zip(first, second))
    print(f"the same vertices: {same}; side by side ÷ one after another, median seconds: "
          f"{median_ratio(rows, name, 'seconds', VARIANTS[1], VARIANTS[0]):.3f}")


if __name__ == "__main__":
    main()
