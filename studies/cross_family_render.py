"""Cross-family rendering: a person of one model family seen in one normal map, fitted with another
family's model (issue 37; docs/studies.md §18). The render counterpart of ``cross_family.py``.

Families and people: benchmarks/families.py. Each person (their own topology) is placed where a
calibrated camera would see them in the model's frame: in the model's units, their centroid on the
model's mean shape's (all families face +z, y up), so nothing but the shape and the exact pose is
left to find (``misplaced``: turned and moved off that place, so the pose is to find too;
docs/studies.md §45). They are rendered as a world-space normal map from a frontal-oblique view (yaw
15–35°, pitch 5°, ``--size``²) and fitted by ``reconstruct`` with each method at its own tuned
settings and the job's default (rigid) alignment, one thread. Scores need no vertex correspondence: 20,000 points drawn
by area on the person's surface, their distance to the fitted surface (leaving out the points beyond
the fit's open boundary: a mask is not asked about the back of a head), as % of the person's RMS
radius, over all points, those on triangles the map shows (``seen``) and the rest (``unseen``).

    python studies/cross_family_render.py --people 2 [--size 256]   # cases run two at a time
    python studies/cross_family_render.py --report                  # tables from the stored rows
    python studies/cross_family_render.py --misplaced 5 [--report]  # the people misplaced (§45)
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from families import FAMILIES  # noqa: E402
from study_runs import run_or_report  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "cross_family_render.json"
RESULTS_MISPLACED = ROOT / "studies" / "results" / "cross_family_render_misplaced.json"
METHODS = ("default", "pca", "statistical", "hybrid", "laplacian")
POINTS = 20_000


def render_case(people: str, model_family: str, seed: int, size: int, misplaced: float = 0.0):
    """The person placed in the model's frame (vertices, in the model's units), their normal map and
    camera, and points on their surface with whether the map shows each. ``misplaced`` > 0: the
    person is then turned by that many degrees about a random axis through their centroid and moved
    by that many % of their RMS radius in a random direction (a camera calibrated to the model's
    frame only so well), so the fit must find the pose, depth included, rather than start on it."""
    import torch
    import trimesh

    from families import METRES_PER_UNIT, family_model, person
    from statfit.renderer import rasterize
    from statfit.renderer.images import render_target
    from statfit.structures.normal_map import NormalMap
    from statfit.synth.sample import camera_for_view

    faces, template = family_model(people).faces, family_model(model_family).template
    shape = person(people, seed) * (METRES_PER_UNIT[people] / METRES_PER_UNIT[model_family])
    shape = shape - shape.mean(axis=0) + template.mean(axis=0)
    if misplaced > 0:
        shape = _misplaced(shape, misplaced, np.random.default_rng(700 + seed))
    yaw = float(np.random.default_rng(900 + seed).uniform(15, 35))
    camera = camera_for_view(shape, yaw, 5.0, size)
    normal_map = NormalMap(*render_target(shape, faces, camera))
    points, triangle = trimesh.Trimesh(shape, faces, process=False).sample(POINTS, return_index=True, seed=seed)
    shown = rasterize(torch.as_tensor(shape), torch.as_tensor(faces, dtype=torch.long), camera).face
    seen = np.isin(triangle, np.unique(shown.numpy()))
    return shape, normal_map, camera, points, seen


def _misplaced(shape: np.ndarray, amount: float, rng: np.random.Generator) -> np.ndarray:
    """``shape`` (N, 3) turned by ``amount`` degrees about a random axis through its centroid and
    moved by ``amount`` % of its RMS radius in a random direction."""
    from scipy.spatial.transform import Rotation

    axis, direction = (v / np.linalg.norm(v) for v in rng.normal(size=(2, 3)))
    centre = shape.mean(axis=0)
    radius = float(np.sqrt(((shape - centre) ** 2).sum(axis=1).mean()))
    turned = Rotation.from_rotvec(np.radians(amount) * axis).apply(shape - centre) + centre
    return turned + amount / 100 * radius * direction


def fit_case(people: str, model_family: str, seed: int, method: str, size: int, misplaced: float = 0.0,
             rigid_modes: str = "auto") -> dict:
    import warnings

    import torch

    torch.set_num_threads(1)
    from cross_family import inside_distance
    from families import family_model
    from statfit.core.threads import flush_denormals_everywhere
    from statfit.render.job import reconstruct

    flush_denormals_everywhere()
    shape, normal_map, camera, points, seen = render_case(people, model_family, seed, size, misplaced)
    model = family_model(model_family)
    row = {"people": people, "model": model_family, "seed": seed, "method": method, "size": size}
    row |= {"misplaced": misplaced} if misplaced > 0 else {}
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            fit = reconstruct(model, normal_map, camera, method, threads=1, rigid_modes=rigid_modes)
    except Exception as exc:   # a refusal is a result too
        return row | {"error": f"{type(exc).__name__}: {exc}".splitlines()[0]}
    row |= {"rigid_free": any("without their rigid motion" in str(w.message) for w in caught)}
    radius = float(np.sqrt(((shape - shape.mean(axis=0)) ** 2).sum(axis=1).mean()))
    distance = 100.0 * inside_distance(points, fit.vertices, model.faces) / radius
    return row | {"all": float(np.nanmean(distance)), "seen": float(np.nanmean(distance[seen])),
                  "unseen": float(np.nanmean(distance[~seen])), "covered": float(np.mean(~np.isnan(distance))),
                  "seconds": fit.seconds}


def report(rows: list[dict]) -> str:
    by = {(r["people"], r["model"], r["seed"], r["method"]): r for r in rows}
    pairs = list(dict.fromkeys((r["people"], r["model"]) for r in rows))
    methods = [m for m in METHODS if any(r["method"] == m for r in rows)]
    lines = ["Mean distance of the person's surface points to the fit, % of the person's RMS radius, over "
             "the people every method fitted (all points; unseen ones in the second table); default ÷ "
             "the best single method on the mean and, in brackets, on its worst case.", "",
             "| people | model | cases | " + " | ".join(methods) + " | default ÷ best (worst case) | unseen: "
             + " | ".join(methods) + " | covered |",
             "|---|---|---|" + "---|" * (2 * len(methods) + 2)]
    for people, model in pairs:
        seeds = sorted({s for (p, m, s, _) in by if (p, m) == (people, model)})
        fitted = [s for s in seeds if all("all" in by.get((people, model, s, m), {}) for m in methods)]
        if not fitted:
            lines.append(f"| {people} | {model} | 0 |" + " – |" * (2 * len(methods) + 2))
            continue
        mean = {m: float(np.mean([by[(people, model, s, m)]["all"] for s in fitted])) for m in methods}
        unseen = {m: float(np.mean([by[(people, model, s, m)]["unseen"] for s in fitted])) for m in methods}
        others = [m for m in methods if m != "default"]
        best = min(mean[m] for m in others)
        worst = max(by[(people, model, s, "default")]["all"] / min(by[(people, model, s, m)]["all"] for m in others)
                    for s in fitted)
        covered = np.mean([by[(people, model, s, "default")]["covered"] for s in fitted])
        lines.append(f"| {people} | {model} | {len(fitted)} | " + " | ".join(f"{mean[m]:.2f}" for m in methods)
                     + f" | {mean['default'] / best:.2f} ({worst:.2f}) | "
                     + " | ".join(f"{unseen[m]:.2f}" for m in methods) + f" | {covered:.0%} |")
    errors = [r for r in rows if "error" in r]
    if errors:
        lines += ["", "Refused: " + "; ".join(f"{r['people']} {r['seed']} → {r['model']} {r['method']}: "
                                              f"{r['error'].split(': ', 1)[-1][:110]}" for r in errors)]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--people", type=int, default=2, help="people per family")
    parser.add_argument("--size", type=int, default=256, help="normal map side (pixels)")
    parser.add_argument("--families", nargs="*", default=list(FAMILIES[:3]), help=f"of {', '.join(FAMILIES)}")
    parser.add_argument("--methods", nargs="*", default=list(METHODS))
    parser.add_argument("--misplaced", type=float, default=0.0,
                        help="turn and move each person by this many degrees and % of their radius off the "
                             "model's mean (the fit must find the pose; rows in RESULTS_MISPLACED)")
    parser.add_argument("--report", action="store_true", help="only print the tables of the stored rows")
    args = parser.parse_args()
    runs = [(p, m, s, method, args.size, args.misplaced) for p in args.families for m in args.families
            for s in range(args.people) for method in args.methods]
    if not args.report:
        from families import build_all

        build_all(args.families, args.people)
    run_or_report(fit_case, runs, RESULTS_MISPLACED if args.misplaced else RESULTS, report, args.report,
                  key=lambda row: (row["people"], row["model"], row["seed"], row["method"], row["size"],
                                   row.get("misplaced", 0.0)))


if __name__ == "__main__":
    main()
