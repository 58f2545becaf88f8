"""A scan's length unit found without landmarks: metric and inch scans of four model families'
people (benchmarks/families.py), each family's model, realistic scans (one view, yaw within ±40°,
any rotation and offset, 4,300 points on the person, clutter 0, 0.5 and 2 per person point).

1. **Where the ratio of sizes lies** (no fit): log10 of the scan's RMS radius over the model's, less
   log10 of the true unit, for metric scans of every family's people under every family's model
   (seeds 0–2): the range that sets ``INCH_BAND`` in statfit/registration/pose/search.py.
   Half faces and face crops of the clean scans too: they reach as far from a power of ten as a
   whole inch scan, so no band of ratios tells inches (docs/studies.md §39).
2. **What the pose search finds** (``estimate_pose``, one thread): for each model, its own people
   and another family's (ICT's for MakeHuman's and the embedded head, MakeHuman's for ICT's and the
   mask), seeds 0–1, each clutter, in mm and in inches: whether the unit found is the true one, and
   for the model's own people the pose's angle from the truth. ~5 min on 2 cores; rows in
   ``studies/results/scan_units.json``. The stored rows were measured with inches read from the
   ratio's band (session 35, dropped for the halves above); a rerun measures the search as it is,
   which refuses or misreads inch scans without landmarks.

    python studies/scan_units.py [--report]
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "studies"))

from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "scan_units.json"
FAMILIES = ("ict", "ict-mask", "makehuman", "embedded")
OTHER_PEOPLE = {"ict": "makehuman", "ict-mask": "makehuman", "makehuman": "ict", "embedded": "ict"}
CLUTTER = (0.0, 0.5, 2.0)
UNITS = ("mm", "in")


def scan_of(people: str, seed: int, clutter: float, units: str, posed: bool = True):
    """A realistic scan of person ``seed`` of ``people``'s family in ``units`` (``posed``: in any
    rotation and offset, else in the person's frame), and what made it."""
    import numpy as np
    from families import family_model, person

    from statfit.synth.scanner import realistic_scan

    rng = np.random.default_rng(seed)
    return realistic_scan(person(people, seed), family_model(people).faces, rng, yaw_deg=rng.uniform(-40, 40),
                          clutter=clutter, units=units, posed=posed)


def true_units(model: str, units: str) -> float:
    """The scan's unit in the model's."""
    from families import METRES_PER_UNIT

    from statfit.synth.scan_options import SCAN_UNITS_PER_METRE

    return METRES_PER_UNIT[model] * SCAN_UNITS_PER_METRE[units]


def ratio_places() -> list[str]:
    """Part 1's table rows: whole scans (each clutter), and the clutter-free scans' halves (split at
    the centroid, left / right / upper / lower) and face crops (the points within 35% of the
    scan's extent of its frontmost point)."""
    import numpy as np
    from families import family_model

    rows = []
    for model in FAMILIES:
        scale, unit = family_model(model).frame.scale, true_units(model, "mm")

        def place(points: np.ndarray) -> float:
            radius = np.sqrt(((points - points.mean(axis=0)) ** 2).sum(axis=1).mean())
            return float(np.log10(radius / scale / unit))

        for people in FAMILIES:
            whole, parts = [], []
            for seed in range(3):
                for clutter in CLUTTER:
                    points = scan_of(people, seed, clutter, "mm", posed=clutter > 0).vertices
                    whole.append(place(points))
                    if clutter == 0:
                        centre = points.mean(axis=0)
                        parts += [place(points[side(points[:, axis], centre[axis])]) for axis in (0, 1)
                                  for side in (np.less, np.greater_equal)]
                        front = np.linalg.norm(points - points[np.argmax(points[:, 2])], axis=1)
                        parts.append(place(points[front < 0.35 * np.ptp(points, axis=0).max()]))
            rows.append(f"| {model} | {people} | {min(whole):+.2f} | {max(whole):+.2f} | {min(parts):+.2f} |")
    return rows


def run_case(model: str, people: str, seed: int, clutter: float, units: str) -> dict:
    import time
    import warnings

    import numpy as np
    import torch
    from families import family_model

    from statfit.errors import StatfitError
    from statfit.registration.pose.search import estimate_pose
    from statfit.structures.scan import Scan

    torch.set_num_threads(1)
    made = scan_of(people, seed, clutter, units)
    row = {"model": model, "people": people, "seed": seed, "clutter": clutter, "units": units}
    start = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            estimate = estimate_pose(family_model(model), Scan.from_mesh(made.vertices, made.faces), threads=1)
    except StatfitError as error:
        return {**row, "refused": str(error), "seconds": time.perf_counter() - start}
    row.update(seconds=time.perf_counter() - start, found=estimate.units, right=bool(
        np.isclose(estimate.units, true_units(model, units), rtol=1e-9)))
    if people == model:
        turn = estimate.transform.rotation.T @ made.transform.rotation
        row["degrees"] = float(np.degrees(np.arccos(np.clip((np.trace(turn) - 1) / 2, -1, 1))))
    return row


def runs() -> list[tuple]:
    return [(model, people, seed, clutter, units) for model in FAMILIES for people in (model, OTHER_PEOPLE[model])
            for seed in range(2) for clutter in CLUTTER for units in UNITS]


def report(rows: list[dict]) -> str:
    lines = ["Part 1: log10(scan RMS radius / model RMS radius / true unit), metric scans, seeds 0–2, clutter "
             + ", ".join(map(str, CLUTTER)), "", "| model | people | whole: least | whole: most | halves and crops: least |",
             "|---|---|---|---|---|",
             *ratio_places(), "", "Part 2: the unit the pose search finds", "",
             "| model | people | units | scans | unit right | refused | own people: largest angle ° "
             "| s a search (mean) |",
             "|---|---|---|---|---|---|---|---|"]
    for model in FAMILIES:
        for people in (model, OTHER_PEOPLE[model]):
            for units in UNITS:
                mine = [r for r in rows if (r["model"], r["people"], r["units"]) == (model, people, units)]
                if not mine:
                    continue
                angles = [r["degrees"] for r in mine if "degrees" in r]
                right, refused = sum(r.get("right", False) for r in mine), sum("refused" in r for r in mine)
                lines.append(f"| {model} | {people} | {units} | {len(mine)} | {right} | {refused} | "
                             f"{f'{max(angles):.1f}' if angles else '–'} | "
                             f"{sum(r['seconds'] for r in mine) / len(mine):.2f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    study_main(__doc__, run_case, runs, RESULTS, report,
               key=lambda r: (r["model"], r["people"], r["seed"], r["clutter"], r["units"]))
