"""Which clutter costs a real scan's face, and whether through the pose or the fit (issue 11, part 3;
docs/studies.md §16).

The real-scans benchmark's six clutter people (docs/benchmarks.md §8: an ICT identity from all 100
modes plus an expression outside the model, a range scan in a random pose and unit), scanned five
ways — no clutter, hair and neck (the benchmark's 50%), hair only, neck and shoulders only, and hair
with its points cut out of the scan (the scalp still hidden: what the scan lacks, without what it
holds that is not the model) — and each fitted twice with ``pca``:

- ``auto``: as a user would (``--align auto``: the pose found without landmarks);
- ``true pose``: the scan put into the model's frame by the pose it was made with (``--align none``),
  with the same clutter rules as the automatic fit chose.

Reported: the face error (mean over the vertices within 3 cm of an inner landmark, mm) and the
automatic pose's rotation error (°).

Off the fitted model's span too: ``--k 50`` fits with the ICT model truncated to its first 50 modes
(the people still use all 100, plus the expression).

    python studies/clutter_parts.py            # ~4 min on 2 cores
    python studies/clutter_parts.py --k 50     # results: studies/results/clutter_parts_k50.json
    python studies/clutter_parts.py --report   # the tables from studies/results/clutter_parts.json
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from study_runs import run_or_report  # noqa: E402  (beside this script)

RESULTS = ROOT / "studies" / "results" / "clutter_parts{}.json"   # "" for the full model, "_k50" for --k 50
SEEDS = range(6)
SCANS = {"no clutter": (0.0, (), False), "hair and neck": (0.5, ("hair", "neck"), False),
         "hair only": (0.5, ("hair",), False), "neck only": (0.5, ("neck",), False),
         "hair, its points cut out": (0.5, ("hair",), True)}


def run_case(seed: int, scan_name: str, k: int | None = None) -> dict:
    import torch

    torch.set_num_threads(1)
    import real_scans
    from scipy.spatial.transform import Rotation
    from statfit.registration.job import register
    from statfit.structures.scan import Scan
    from statfit.core.threads import flush_denormals_everywhere

    flush_denormals_everywhere()
    model = real_scans._model() if k is None else real_scans._model().truncated(k)
    template = model.template
    near = (np.linalg.norm(template[:, None] - template[model.landmarks][None], axis=-1).min(axis=1)
            < real_scans.FACE_RADIUS_CM)
    clutter, parts, cut_out = SCANS[scan_name]
    made, units = real_scans._person(seed, clutter, parts)
    mm = real_scans.MM_PER_UNIT[units]
    faces = made.faces[made.on_shape[made.faces].all(axis=1)] if cut_out else made.faces
    scan = Scan.from_mesh(made.vertices, faces)
    face_mm = lambda vertices: float(np.linalg.norm(vertices - made.truth, axis=1)[near].mean() * mm)  # noqa: E731
    auto = register(model, scan, "pca", threads=1)
    truth = made.transform
    in_model = Scan(truth.inverse_apply(scan.points), scan.normals @ truth.rotation)
    at_truth = register(model, in_model, "pca", align="none", clutter=auto.pose["clutter_rules"], threads=1)
    angle = float(np.degrees(Rotation.from_matrix(auto.transform.rotation @ truth.rotation.T).magnitude()))
    return {"seed": seed, "scan": scan_name, "clutter_ratio": made.clutter_ratio, "matched": auto.pose["matched"],
            "clutter_rules": auto.pose["clutter_rules"], "pose_deg": angle, "auto_mm": face_mm(auto.vertices),
            "true_pose_mm": face_mm(truth.apply(at_truth.vertices))}


def report(rows: list[dict]) -> str:
    lines = ["| scan | clutter per face point | clutter rules on | pose error ° (mean, max) | face mm, auto pose "
             "| face mm, true pose | auto per scan |", "|---|---|---|---|---|---|---|"]
    for name in SCANS:
        mine = sorted((r for r in rows if r["scan"] == name), key=lambda r: r["seed"])
        if not mine:
            continue
        deg = np.array([r["pose_deg"] for r in mine])
        lines.append(f"| {name} | {np.mean([r['clutter_ratio'] for r in mine]):.2f} "
                     f"| {sum(r['clutter_rules'] for r in mine)} of {len(mine)} | {deg.mean():.2f}, {deg.max():.2f} "
                     f"| {np.mean([r['auto_mm'] for r in mine]):.2f} | {np.mean([r['true_pose_mm'] for r in mine]):.2f} "
                     "| " + ", ".join(f"{r['auto_mm']:.2f}" for r in mine) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--k", type=int, default=None, help="fit with the model's first K modes only")
    parser.add_argument("--report", action="store_true", help="only print the tables of the stored results")
    args = parser.parse_args()
    results = RESULTS.with_name(RESULTS.name.format("" if args.k is None else f"_k{args.k}"))
    run_or_report(run_case, [(seed, name, args.k) for name in SCANS for seed in SEEDS], results, report, args.report)


if __name__ == "__main__":
    main()
