"""Does a point cloud's own normals column help? A point cloud's normals are estimated from its
nearest neighbours (statfit/structures/scan.py), whatever normals its file holds (docs/formats.md).
Here each realistic ICT scan (benchmarks/families.py's people; one view, yaw within ±40°, any pose,
mm, 4,300 points, clutter 0 and 0.5; seeds 0–7) is drawn once by area and registered twice with the
default: with its points' true normals (its triangles', oriented outwards), and with normals
estimated from the points alone. Score: mean face-vertex error, mm. One thread a fit.

    python studies/cloud_normals.py [--report]

~3 min on 2 cores; rows in studies/results/cloud_normals.json (docs/formats.md, "Scans").
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "studies"))

from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "cloud_normals.json"
SEEDS, CLUTTER = range(8), (0.0, 0.5)


def run_case(seed: int, clutter: float) -> dict:
    import warnings

    import numpy as np
    import torch
    from families import family_model, person

    from statfit.registration.job import register
    from statfit.structures.scan import Scan
    from statfit.synth.scanner import realistic_scan

    torch.set_num_threads(1)
    model = family_model("ict")
    rng = np.random.default_rng(seed)
    made = realistic_scan(person("ict", seed), model.faces, rng, yaw_deg=rng.uniform(-40, 40), clutter=clutter,
                          units="mm", posed=True)
    drawn = Scan.from_mesh(made.vertices, made.faces)
    row = {"seed": seed, "clutter": clutter}
    for name, scan in (("true", Scan(drawn.points, drawn.normals)), ("estimated", Scan.from_points(drawn.points))):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fitted = register(model, scan, threads=1).vertices
        row[name] = float(np.linalg.norm(fitted - made.truth, axis=1)[model.regions["face"]].mean())
    return row


def runs() -> list[tuple]:
    return [(seed, clutter) for seed in SEEDS for clutter in CLUTTER]


def report(rows: list[dict]) -> str:
    lines = ["| clutter | scans | true normals: face mm | estimated | true better |", "|---|---|---|---|---|"]
    for clutter in (*CLUTTER, None):
        mine = [r for r in rows if clutter is None or r["clutter"] == clutter]
        true, estimated = (sum(r[k] for r in mine) / len(mine) for k in ("true", "estimated"))
        lines.append(f"| {'all' if clutter is None else clutter} | {len(mine)} | {true:.3f} | {estimated:.3f} | "
                     f"{sum(r['true'] < r['estimated'] for r in mine)} of {len(mine)} |")
    return "\n".join(lines)


if __name__ == "__main__":
    study_main(__doc__, run_case, runs, RESULTS, report, key=lambda r: (r["seed"], r["clutter"]))
