"""The covering silhouette: a map that shows part of what the model makes (issue 37; docs/studies.md §24).

§18's two-sided silhouette term assumes the map's outline is the model's; its one-sided term, a
model of part of what the map shows (a face mask in a map of a head). The opposite case is common
too: a map whose foreground is part of the person (a face cut out of a photo by a skin or face
mask), fitted with a head model. The covering term counts only the map's pixels the model leaves
uncovered, so the model must cover the map's foreground but may reach beyond it.

This refits §18's cases whose model is a whole head (ICT's, MakeHuman's: 12 cases, 256², one
thread) with the render default and ``silhouette="covering"``, beside §18's stored rows of every
method with the term ``auto`` gives them (two-sided for these models): on the mask family's people
(the map shows the face only), what the right term gains; on whole heads, what the wrong one costs.

    python studies/covering_silhouette.py            # 12 default fits, two at a time; ~4 min on 2 cores
    python studies/covering_silhouette.py --report   # the table from the stored rows
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from render_fit_residual import OTHERS, RESULTS, SIZE, stored  # noqa: E402  (sets the benchmarks path too)
from study_runs import study_main  # noqa: E402

ROWS = RESULTS / "covering_silhouette.json"
HEAD_MODELS = ("ict", "makehuman")


def fit_case(people: str, model_family: str, seed: int) -> dict:
    """§18's case fitted with the render default and the covering silhouette: §18's scores."""
    import torch

    torch.set_num_threads(1)
    from cross_family import inside_distance
    from cross_family_render import render_case
    from families import family_model
    from statfit.core.threads import flush_denormals_everywhere
    from statfit.render.job import reconstruct

    flush_denormals_everywhere()
    shape, normal_map, camera, points, seen = render_case(people, model_family, seed, SIZE)
    model = family_model(model_family)
    fit = reconstruct(model, normal_map, camera, "default", threads=1, silhouette="covering")
    radius = float(np.sqrt(((shape - shape.mean(axis=0)) ** 2).sum(axis=1).mean()))
    distance = 100.0 * inside_distance(points, fit.vertices, model.faces) / radius
    return {"people": people, "model": model_family, "seed": seed, "all": float(np.nanmean(distance)),
            "seen": float(np.nanmean(distance[seen])), "unseen": float(np.nanmean(distance[~seen])),
            "seconds": fit.seconds}


def runs() -> list[tuple]:
    return sorted({key[:3] for key in stored() if key[3] == "default" and key[1] in HEAD_MODELS})


def report(rows: list[dict]) -> str:
    by = stored()
    lines = ["Mean distance of the person's surface points to the fit, % of the person's RMS radius (§18's "
             "score): the default with the covering silhouette, and §18's stored rows (two-sided: what `auto` "
             "gives a head model).", "",
             "| people | model | seed | default, covering | default, two-sided | best other, two-sided | "
             "covering ÷ two-sided |", "|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda row: (row["people"], row["model"], row["seed"])):
        key = (r["people"], r["model"], r["seed"])
        others = {m: by[(*key, m)]["all"] for m in OTHERS if (*key, m) in by}
        best = min(others, key=others.get)
        default = by[(*key, "default")]["all"]
        lines.append(f"| {key[0]} | {key[1]} | {key[2]} | {r['all']:.2f} | {default:.2f} | {others[best]:.2f} "
                     f"({best}) | {r['all'] / default:.2f} |")
    return "\n".join(lines)


def main() -> None:
    study_main(__doc__, fit_case, runs, ROWS, report, lambda row: (row["people"], row["model"], row["seed"]))


if __name__ == "__main__":
    main()
