"""The scalp as a region: leaving where hair can grow to the hair, in the pose and in the fit
(issue 11, part 3; docs/studies.md §16, "The scalp as a region").

The real-scans benchmark's people (docs/benchmarks.md §8: an ICT identity from all 100 modes plus an
expression outside the model, a range scan in a random pose and unit, hair, neck and shoulders worth
50% of the face's points), fitted as a user would (``--align auto``, the default method) under
variants of :func:`statfit.model.statmodel.scalp_triangles`' use:

- ``none``: the code before the region (the polish's second pass on the face alone, the hair being
  only what lies beyond a face fit's scalp);
- ``pose only`` / ``fit only`` / ``pose and fit`` (shipped): where the region is used;
- the region's two sizes varied (SCALP_ABOVE, SCALP_BEHIND, RMS radii).

Reported per variant: the automatic pose's rotation error on people 0–49 with clutter (°), and the
face error (mean over the vertices within 3 cm of an inner landmark, mm) of people 0–17 scanned
without and with clutter (the same scanner draws otherwise), and its change.

    python studies/scalp_region.py            # ~16 min on 2 cores
    python studies/scalp_region.py --report   # the table from studies/results/scalp_region.json
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from study_runs import run_or_report  # noqa: E402  (beside this script)

RESULTS = ROOT / "studies" / "results" / "scalp_region.json"
POSE_PEOPLE = range(50)
FACE_PEOPLE = range(18)
METHOD = "default"
# name: (region in the pose, region in the fit, SCALP_ABOVE, SCALP_BEHIND)
VARIANTS = {"none (before)": (False, False, 0.15, 0.3),
            "pose only": (True, False, 0.15, 0.3),
            "fit only": (False, True, 0.15, 0.3),
            "pose and fit (shipped)": (True, True, 0.15, 0.3),
            "above 0.0": (True, True, 0.0, 0.3),
            "above 0.3": (True, True, 0.3, 0.3),
            "behind 0.8": (True, True, 0.15, 0.8)}


def _use(variant: str) -> None:
    """Set the modules up for ``variant`` (every call, so a worker can run any variant next)."""
    import importlib

    model_module = importlib.import_module("statfit.model.statmodel")
    pose_module = importlib.import_module("statfit.registration.pose.search")
    fit_module = importlib.import_module("statfit.registration.posed")
    in_pose, in_fit, above, behind = VARIANTS[variant]
    model_module.SCALP_ABOVE, model_module.SCALP_BEHIND = above, behind
    scalp = model_module.scalp_triangles
    pose_module.scalp_triangles = scalp if in_pose else (lambda model: None)
    fit_module.scalp_triangles = scalp if in_fit else (lambda model: np.zeros(len(model.faces), dtype=bool))


def run_case(variant: str, seed: int, clutter: float) -> dict:
    import torch

    torch.set_num_threads(1)
    import real_scans
    from scipy.spatial.transform import Rotation
    from statfit.registration.pose.search import estimate_pose
    from statfit.registration.job import register
    from statfit.structures.scan import Scan
    from statfit.core.threads import flush_denormals_everywhere

    flush_denormals_everywhere()
    _use(variant)
    model = real_scans._model()
    made, units = real_scans._person(seed, clutter)
    scan = Scan.from_mesh(made.vertices, made.faces)
    row = {"variant": variant, "seed": seed, "clutter": clutter}
    if seed in FACE_PEOPLE:
        template = model.template
        near = (np.linalg.norm(template[:, None] - template[model.landmarks][None], axis=-1).min(axis=1)
                < real_scans.FACE_RADIUS_CM)
        fit = register(model, scan, METHOD, threads=1)
        rotation = fit.transform.rotation
        row.update(face_mm=float(np.linalg.norm(fit.vertices - made.truth, axis=1)[near].mean()
                                 * real_scans.MM_PER_UNIT[units]), clutter_rules=fit.pose["clutter_rules"])
    else:
        rotation = estimate_pose(model, scan).transform.rotation
    row["pose_deg"] = float(np.degrees(Rotation.from_matrix(rotation @ made.transform.rotation.T).magnitude()))
    return row


def report(rows: list[dict]) -> str:
    lines = ["| variant | pose ° with clutter, 50 people: mean, median, max | beyond 1.5° | face mm clean "
             "| face mm clutter | change | people +25% or more |", "|---|---|---|---|---|---|---|"]
    for variant in VARIANTS:
        mine = [r for r in rows if r["variant"] == variant]
        if not mine:
            continue
        pose = np.array([r["pose_deg"] for r in mine if r["clutter"] > 0])
        faces = {(r["seed"], r["clutter"]): r["face_mm"] for r in mine if "face_mm" in r}
        seeds = sorted({seed for seed, _ in faces})
        clean = np.array([faces[seed, 0.0] for seed in seeds])
        cluttered = np.array([faces[seed, 0.5] for seed in seeds])
        change = 100 * (cluttered.mean() / clean.mean() - 1)
        lines.append(f"| {variant} | {pose.mean():.2f}, {np.median(pose):.2f}, {pose.max():.2f} | {(pose > 1.5).sum()} "
                     f"| {clean.mean():.3f} | {cluttered.mean():.3f} | {change:+.1f}% "
                     f"| {(cluttered > 1.25 * clean).sum()} of {len(seeds)} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--report", action="store_true", help="only print the table of the stored results")
    args = parser.parse_args()
    runs = [(variant, seed, clutter) for variant in VARIANTS for seed in POSE_PEOPLE
            for clutter in ((0.0, 0.5) if seed in FACE_PEOPLE else (0.5,))]
    runs.sort(key=lambda run: run[1] not in FACE_PEOPLE)   # the long fits first, the short poses fill in
    run_or_report(run_case, runs, RESULTS, report, args.report)


if __name__ == "__main__":
    main()
