"""The settling polish (docs/studies.md §41) on sparse and dense scans: §41 measured it at 4,300 points
only. The same people as §40's density cases (the three real families' people under their own models,
seeds 6–7, realistic scans in mm) at 1,000 and 20,000 points, clutter 0 and 2 per person point, each
searched with the last two polishes stopped at 12 steps ("before") and settling ("both", as shipped),
in one process (``estimate_pose``, one thread). A row keeps each search's decision, the pose's angle
from the truth, the person's offset from their place (not for MakeHuman, whose head modes move the
head) and seconds.

    python studies/polish_settle_density.py [--report]

~5 min on 2 cores; rows in studies/results/polish_settle_density.json.
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "studies"))

from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "polish_settle_density.json"
FAMILIES, SEEDS, POINTS, CLUTTER = ("ict", "ict-mask", "makehuman"), (6, 7), (1000, 20000), (0.0, 2.0)
VARIANTS = ("before", "both")


def run_case(family: str, seed: int, points: int, clutter: float) -> dict:
    import numpy as np
    import torch
    from families import family_model, person
    from polish_settle import search_with_variant

    from statfit.registration.pose.hypotheses import angle_between
    from statfit.structures.scan import Scan
    from statfit.synth.scanner import realistic_scan

    torch.set_num_threads(1)
    model = family_model(family)
    rng = np.random.default_rng(seed)
    made = realistic_scan(person(family, seed), model.faces, rng, points, yaw_deg=rng.uniform(-40, 40),
                          clutter=clutter, units="mm", posed=True)
    scan = Scan.from_mesh(made.vertices, made.faces)
    row = {"family": family, "seed": seed, "points": points, "clutter": clutter}
    for variant in VARIANTS:
        searched = search_with_variant(model, scan, variant)
        found = searched.pop("found")
        row[f"decision_{variant}"], row[f"seconds_{variant}"] = searched["decision"], searched["seconds"]
        if found is not None:
            row[f"degrees_{variant}"] = angle_between(found.transform.rotation, made.transform.rotation)
            own = person(family, seed)
            offset = (found.transform.apply(own) - made.transform.apply(own)).mean(axis=0)
            row[f"offset_mm_{variant}"] = float(np.linalg.norm(offset))
    return row


def runs() -> list[tuple]:
    return [(f, s, p, c) for f in FAMILIES for p in POINTS for c in CLUTTER for s in SEEDS]


def report(rows: list[dict]) -> str:
    import numpy as np

    lines = ["Sparse and dense scans, the last polishes stopped at 12 steps → settling: refused, the pose's mean angle "
             "(°), the person's mean offset (mm; MakeHuman: –) and the search's mean seconds", "",
             "| people and model | points | clutter | scans | refused | angle ° | offset mm | s |", "|---|---|---|---|---|---|---|---|"]
    for family in FAMILIES:
        for points in POINTS:
            for clutter in CLUTTER:
                mine = [r for r in rows if (r["family"], r["points"], r["clutter"]) == (family, points, clutter)]
                refused = " → ".join(str(sum(r[f"decision_{v}"] == "refuse" for r in mine)) for v in VARIANTS)
                both = [r for r in mine if all(f"degrees_{v}" in r for v in VARIANTS)]
                angle = " → ".join(f"{np.mean([r[f'degrees_{v}'] for r in both]):.2f}" for v in VARIANTS) if both else "–"
                offset = (" → ".join(f"{np.mean([r[f'offset_mm_{v}'] for r in both]):.2f}" for v in VARIANTS)
                          if both and family != "makehuman" else "–")
                seconds = " → ".join(f"{np.mean([r[f'seconds_{v}'] for r in mine]):.2f}" for v in VARIANTS)
                lines.append(f"| {family} | {points} | {clutter} | {len(mine)} | {refused} | {angle} | {offset} | {seconds} |")
    return "\n".join(lines)


if __name__ == "__main__":
    study_main(__doc__, run_case, runs, RESULTS, report,
               key=lambda row: (row["family"], row["seed"], row["points"], row["clutter"]))
