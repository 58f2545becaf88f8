"""The default render fit's time with ICT's modes kept as built (``--rigid-modes keep``) and under
``auto``, which aligns a second time without their rigid motion where the first alignment moved the
model off its place (docs/studies.md §46), side by side in one process on one thread: ICT's maps
(benchmarks/cases.py), the person as the case places them (the rule does not fire) and misplaced
(turned by 5° about a fixed tilted axis and moved by 5% of the radius: it fires), the two settings
alternating, ``--rounds`` times each. Prints, per fit, the whole fit's, the alignment's and the
loop's seconds and the error (% of the radius, per vertex); then the medians' ratios.

    python benchmarks/rigid_modes_time.py [--size 512] [--rounds 2] [--cases jaw-open]
"""
from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
import torch

from cases import NormalCase, ict_model, normal_case, relative_errors
from common import alternate, median_ratio

TURN_DEG, MOVE = 5.0, 0.05
AXIS = np.array([0.3, 0.9, 0.3]) / np.linalg.norm([0.3, 0.9, 0.3])


def misplaced(named: NormalCase, size: int) -> NormalCase:
    """``named`` with its person turned by TURN_DEG about AXIS through their centroid and moved by MOVE
    of their RMS radius, seen again by a camera looking at them as the case's did."""
    from scipy.spatial.transform import Rotation

    from statfit.geometry.metrics import visible_vertices
    from statfit.renderer.images import render_target
    from statfit.structures.normal_map import NormalMap

    target = named.target
    centre = target.mean(axis=0)
    radius = float(np.sqrt(((target - centre) ** 2).sum(axis=1).mean()))
    moved = Rotation.from_rotvec(np.radians(TURN_DEG) * AXIS).apply(target - centre) + centre
    moved = moved + MOVE * radius * np.array([1.0, -0.5, 0.0]) / np.linalg.norm([1.0, -0.5, 0.0])
    faces = ict_model().faces
    camera = named.camera      # the case's camera: the person moved in its view
    return NormalCase(named.name, moved, NormalMap(*render_target(moved, faces, camera)), camera,
                      visible_vertices(moved, faces, camera))


def fit(named: NormalCase, rule: str) -> dict:
    """One default fit of ``named``'s map under ``rule``: seconds (whole, alignment, loop), error, fired."""
    from statfit.render.job import reconstruct

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        started = time.perf_counter()
        result = reconstruct(ict_model(), named.normal_map, named.camera, "default", threads=1, rigid_modes=rule)
        whole = time.perf_counter() - started
    alignment = result.stage_seconds.get("alignment", 0.0)
    return {"whole": whole, "alignment": alignment, "loop": whole - alignment,
            "error": 100 * relative_errors(result.vertices, named.target, named.observed)["all"],
            "fired": any("off where they place" in str(w.message) for w in caught)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--cases", nargs="*", default=["jaw-open"])
    args = parser.parse_args()
    torch.set_num_threads(1)
    names = [f"{case} {placement}" for case in args.cases for placement in ("placed", "misplaced")]

    def prepare(name: str) -> NormalCase:
        case, placement = name.split()
        named = normal_case(case, args.size)
        return misplaced(named, args.size) if placement == "misplaced" else named

    rows = alternate(names, prepare, ("keep", "auto"), args.rounds, fit,
                     lambda rule, row: f"{rule:4s} whole {row['whole']:6.1f} s, alignment {row['alignment']:5.1f} s, "
                                       f"loop {row['loop']:6.1f} s, error {row['error']:.3f}%"
                                       f"{' (fired)' if row['fired'] else ''}")
    for name in names:
        print(f"{name}: auto ÷ keep, medians: whole {median_ratio(rows, name, 'whole', 'auto', 'keep'):.3f}, "
              f"alignment {median_ratio(rows, name, 'alignment', 'auto', 'keep'):.3f}, "
              f"error {median_ratio(rows, name, 'error', 'auto', 'keep'):.3f}")


if __name__ == "__main__":
    main()
