"""Would a fallback help `render` as it helps `register`? The render default's image residual on §18's
cross-family cases (issue 37, part 3; docs/studies.md §23).

`register`'s default falls back to ``laplacian`` where its fit leaves the scan far away (§23). For
`render` the counterpart of that residual is how far the fit's rendered normals are from the map's:
the mean and median angle over the pixels both cover (degrees), and the share of the pixels either
covers that only one does (the silhouettes' disagreement). This refits §18's 18 cross-family cases
(256², one thread) with the render default, records those residuals beside §18's all-point error, and
sets them against the stored errors of every other method (studies/results/cross_family_render.json).

    python studies/render_fit_residual.py            # 18 default fits, two at a time; ~7 min on 2 cores
    python studies/render_fit_residual.py --report   # the table from the stored rows
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results"
ROWS = RESULTS / "render_fit_residual.json"
STORED = RESULTS / "cross_family_render.json"
SIZE = 256
OTHERS = ("pca", "statistical", "hybrid", "laplacian")


def image_residual(vertices: np.ndarray, faces: np.ndarray, normal_map, camera) -> dict:
    """The fit's rendered camera-space normals against the map's: mean and median angle (degrees)
    over the pixels both cover, and the pixels only one covers ÷ those either covers."""
    from statfit.render.job import camera_space_normals
    from statfit.render.preview import angular_error
    from statfit.renderer.images import render_target

    target = camera_space_normals(normal_map, camera, "world", "opencv")
    fitted, covered = render_target(vertices, faces, camera, space="camera")
    angles = angular_error(fitted.astype(np.float64), target)[covered & normal_map.mask]
    return {"angle": float(angles.mean()), "angle_median": float(np.median(angles)),
            "silhouette": float((covered ^ normal_map.mask).sum() / (covered | normal_map.mask).sum())}


def fit_case(people: str, model_family: str, seed: int) -> dict:
    """§18's case fitted with the render default: its all-point error (§18's score) and residuals."""
    import torch

    torch.set_num_threads(1)
    from cross_family import inside_distance
    from cross_family_render import render_case
    from families import family_model
    from statfit.core.threads import flush_denormals_everywhere
    from statfit.render.job import reconstruct

    flush_denormals_everywhere()
    shape, normal_map, camera, points, _ = render_case(people, model_family, seed, SIZE)
    model = family_model(model_family)
    fit = reconstruct(model, normal_map, camera, "default", threads=1)
    radius = float(np.sqrt(((shape - shape.mean(axis=0)) ** 2).sum(axis=1).mean()))
    distance = 100.0 * inside_distance(points, fit.vertices, model.faces) / radius
    return {"people": people, "model": model_family, "seed": seed, "all": float(np.nanmean(distance)),
            **image_residual(fit.vertices, model.faces, normal_map, camera), "seconds": fit.seconds}


def stored() -> dict:
    return {(r["people"], r["model"], r["seed"], r["method"]): r for r in json.loads(STORED.read_text()) if "all" in r}


def report(rows: list[dict]) -> str:
    by = stored()
    lines = ["§18's cases by the default's mean angle residual: the default's all-point error (% of the person's "
             "radius; now, and §18's stored row), `laplacian`'s and the best other method's (stored).", "",
             "| people | model | seed | angle ° (median) | silhouettes disagree | default | stored | laplacian | "
             "best other | laplacian better |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda row: row["angle"]):
        key = (r["people"], r["model"], r["seed"])
        others = {m: by[(*key, m)]["all"] for m in OTHERS if (*key, m) in by}
        best = min(others, key=others.get)
        lines.append(f"| {key[0]} | {key[1]} | {key[2]} | {r['angle']:.2f} ({r['angle_median']:.2f}) | "
                     f"{r['silhouette']:.2%} | {r['all']:.2f} | {by[(*key, 'default')]['all']:.2f} | "
                     f"{others['laplacian']:.2f} | {others[best]:.2f} ({best}) | "
                     f"{'yes' if others['laplacian'] < r['all'] else 'no'} |")
    return "\n".join(lines)


def main() -> None:
    study_main(__doc__, fit_case, lambda: sorted({key[:3] for key in stored() if key[3] == "default"}), ROWS, report,
               lambda row: (row["people"], row["model"], row["seed"]))


if __name__ == "__main__":
    main()
