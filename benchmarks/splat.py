"""Part 10: splatting — the surfel renderer's forward + backward time at 256² on the ICT head (1 and
3 splats per triangle, 1 and 2 threads), and a default `statfit splat` fit on 24 views at 256²
(issue 15's targets: the renderer well under a second, the fit ≤ 10 min on this 2-core CPU).

The renderer runs in this process at a chosen thread count (median of 5 after a warm-up); the fit
runs as the commands a user types, in a fresh process (wall seconds include Python's start, the
model's load and the held-out scoring). Accuracy per method is the study's (studies/study_splat.py,
docs/studies.md §14).
"""
from __future__ import annotations

import json
import tempfile
from pathlib import Path

from common import ICT_EXPRESSIONS, ICT_MODEL, Section, markdown_table, median_ms, timed_statfit as statfit

FULL = {"size": 256, "views": 24, "iterations": None}
QUICK = {"size": 96, "views": 6, "iterations": 20}


def renderer_ms(per_triangle: int, threads: int, size: int) -> tuple[int, int, float]:
    """Splat count, (splat, pixel) pairs and the median forward + backward milliseconds."""
    import numpy as np
    import torch

    from statfit.model.importers.cache import open_model
    from statfit.renderer import MeshSplats, render_surfels
    from statfit.synth.sample import camera_for_view

    torch.set_num_threads(threads)
    model = open_model(ICT_MODEL)
    vertices = torch.tensor(model.template, dtype=torch.float32, requires_grad=True)
    splats = MeshSplats.on(torch.as_tensor(model.faces, dtype=torch.long), per_triangle)
    camera = camera_for_view(np.asarray(model.template), 20.0, 0.0, size)
    pairs = []

    def step() -> None:
        image = render_surfels(splats.surfels(vertices), camera)
        (image.colour.sum() + image.alpha.sum()).backward()
        pairs.append(image.pairs)

    ms = median_ms(step, 5)   # before reading ``pairs``, which the steps fill
    return len(splats), pairs[0], ms


def run(quick: bool, device: str, image_dir) -> Section:
    config = QUICK if quick else FULL
    rows = []
    renderer = []
    for per_triangle in (1, 3):
        for threads in (1, 2):
            count, pairs, ms = renderer_ms(per_triangle, threads, config["size"])
            renderer.append({"splats": count, "pairs": pairs, "threads": threads, "ms": ms})
            rows.append([f"{count:,}", f"{pairs:,}", threads, ms])
    with tempfile.TemporaryDirectory() as folder:
        views = str(Path(folder) / "views")
        statfit("synth", "views", "--model", str(ICT_MODEL), "--delta", str(ICT_EXPRESSIONS), "--delta-name",
                "jawOpen", "--seed", "2", "--views", str(config["views"]), "--size", str(config["size"]), "--out", views)
        extra = ["--iterations", str(config["iterations"])] if config["iterations"] else []
        wall, out = statfit("splat", views, "--model", str(ICT_MODEL), "--out", str(Path(folder) / "fit.ply"),
                            "--json", "-q", *extra)
    summary = json.loads(out)
    data = {**config, "renderer": renderer, "fit_wall_seconds": wall, "fit_seconds": summary["seconds"],
            "fit_stage_seconds": summary["stage_seconds"], "held_out": summary["held_out"]}
    text = (f"Renderer, forward + backward of one {config['size']}² view of the ICT head (median of 5):\n\n"
            + markdown_table(["splats", "pairs", "threads", "ms"], rows)
            + f"\n\n`statfit splat` default, {config['views']} views at {config['size']}² (ICT, jawOpen, seed 2): "
            f"{wall:.0f} s wall, of which the fit {summary['seconds']:.0f} s (target ≤ 600 s); held-out PSNR "
            f"{summary['held_out']['psnr']:.2f} dB. Stages (s): "
            + ", ".join(f"{k} {v:.1f}" for k, v in summary["stage_seconds"].items()) + ".")
    return Section("splat", "Splatting: the surfel renderer and a default fit", text, data=data)
