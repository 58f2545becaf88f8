"""Many scans registered, and many normal maps rendered, in one program (issue 38, part 3):
``register_many`` against one ``register`` after another, ``reconstruct_many`` against one
``reconstruct`` after another, side by side in one run.

ICT scans of 16 people (identity samples, one view each, yaw within ±40°, 4,300 points), the default
pipeline, one thread: seconds per fit one by one and with 4, 8 and 16 fits stepped together; each
fit's mean vertex error against the person (mm), and how far the fits together lie from the fits
alone (mm, per vertex). Then the torch ops and host waits of one iteration of the stage stepped
together (paper ``statistical``, the embedded model, ``align="none"``, counted as
``../shared/tools/sync_count.py`` counts them) for 1 and for 8 fits: what a GPU pays per launch.

Normal maps: 8 ICT people (identity samples, yaw within ±30°, 256² maps), the render default, one
thread: seconds per fit one by one and with 4 and 8 maps fitted together; the mean vertex error
against the person and the distance from the fits alone (mm); ops and waits of one iteration for 1
and 8 maps together (paper ``statistical``, the embedded model at 256², ``align="none"``).

    python benchmarks/run.py --only together [--device cuda]
"""
from __future__ import annotations

import time

import numpy as np

from common import ICT_MODEL, Section

PEOPLE, QUICK_PEOPLE = 16, 4
GROUPS, QUICK_GROUPS = (4, 8, 16), (2, 4)
MAPS, QUICK_MAPS = 8, 2
MAP_GROUPS, QUICK_MAP_GROUPS = (4, 8), (2,)
MAP_SIZE, QUICK_MAP_SIZE = 256, 96
MM_PER_UNIT = 10.0    # ICT is in cm


def people(model, count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(person (N, 3), scan (4,300, 3)) for ``count`` seeded identity samples of ``model``."""
    from statfit.synth.sample import sample_target, scan_from_view

    made = []
    for seed in range(count):
        rng = np.random.default_rng(200 + seed)
        person = sample_target(model, rng)
        made.append((person, scan_from_view(person, model.faces, rng, 4300, float(rng.uniform(-40, 40)))))
    return made


def viewed(model, count: int, size: int) -> list[tuple[np.ndarray, object, object]]:
    """(person (N, 3), normal map, camera) for ``count`` seeded identity samples of ``model``."""
    from statfit.renderer.images import render_target
    from statfit.structures.normal_map import NormalMap
    from statfit.synth.sample import camera_for_view, sample_target

    made = []
    for seed in range(count):
        rng = np.random.default_rng(300 + seed)
        person = sample_target(model, rng)
        camera = camera_for_view(person, float(rng.uniform(-30, 30)), float(rng.uniform(-10, 10)), size)
        made.append((person, NormalMap(*render_target(person, model.faces, camera)), camera))
    return made


def ops_per_iteration(model, points: np.ndarray, fits: int, device: str) -> tuple[float, float]:
    """(ops, host waits) per iteration of ``fits`` paper-statistical fits stepped together."""
    from gpu import per_iteration
    from statfit.registration.many import register_many

    return per_iteration(lambda it: register_many(model, [points] * fits, "statistical", preset="paper",
                                                  align="none", device=device, iterations=it)[0].fit.iterations)


def render_ops_per_iteration(model, normal_map, camera, fits: int, device: str) -> tuple[float, float]:
    """(ops, host waits) per iteration of ``fits`` paper-statistical render fits stepped together."""
    from gpu import per_iteration
    from statfit.render.many import reconstruct_many

    return per_iteration(lambda it: reconstruct_many(model, [normal_map] * fits, [camera] * fits, "statistical",
                                                     preset="paper", align="none", device=device,
                                                     iterations=it)[0].fit.iterations)


def side_by_side(alone: list[np.ndarray], seconds: float, groups: dict[int, tuple[list[np.ndarray], float]],
                 persons: list[np.ndarray]) -> list[dict]:
    """One row for the fits alone and one per group size: seconds per fit, mean vertex error (mm)
    and median distance from the fits alone (mm)."""
    def error_mm(vertices: list[np.ndarray]) -> float:
        return float(np.mean([np.linalg.norm(v - p, axis=1).mean() for v, p in zip(vertices, persons)]) * MM_PER_UNIT)

    rows = [{"together": 1, "s_per_fit": seconds, "error_mm": error_mm(alone), "from_alone_mm": 0.0}]
    for size, (fits, per_fit) in groups.items():
        apart = np.median([np.linalg.norm(a - b, axis=1).mean() for a, b in zip(fits, alone)]) * MM_PER_UNIT
        rows.append({"together": size, "s_per_fit": per_fit, "error_mm": error_mm(fits), "from_alone_mm": float(apart)})
    return rows


def table(rows: list[dict]) -> list[str]:
    lines = ["| fits together | s per fit | × one by one | mean vertex error (mm) | median distance from the fit "
             "alone (mm) |", "|---|---|---|---|---|"]
    for row in rows:
        lines.append(f"| {row['together']} | {row['s_per_fit']:.2f} | {row['s_per_fit'] / rows[0]['s_per_fit']:.2f} | "
                     f"{row['error_mm']:.4f} | {row['from_alone_mm']:.4f} |")
    return lines


def timed_groups(fit_group, inputs: list, sizes) -> dict[int, tuple[list[np.ndarray], float]]:
    """For each group size: the fits of ``inputs`` in groups of that size (``fit_group(list)`` → the
    fits' vertices), and the seconds per fit."""
    groups = {}
    for size in sizes:
        started = time.perf_counter()
        fits = [v for first in range(0, len(inputs), size) for v in fit_group(inputs[first:first + size])]
        groups[size] = (fits, (time.perf_counter() - started) / len(inputs))
    return groups


def run(quick: bool, device: str, image_dir) -> Section:
    import torch

    from statfit.model.statmodel import default_model_path, load_model
    from statfit.registration.job import register
    from statfit.registration.many import register_many
    from statfit.render.job import reconstruct
    from statfit.render.many import reconstruct_many

    torch.set_num_threads(1)
    model = load_model(ICT_MODEL)
    cases = people(model, QUICK_PEOPLE if quick else PEOPLE)
    persons, scans = zip(*cases)
    register(model, scans[0], device=device)          # warm-up: caches, a GPU's start
    started = time.perf_counter()
    alone = [register(model, scan, device=device).vertices for scan in scans]
    seconds = (time.perf_counter() - started) / len(scans)
    groups = timed_groups(lambda group: [out.fit.vertices for out in register_many(model, list(group), device=device)],
                          list(scans), QUICK_GROUPS if quick else GROUPS)
    rows = side_by_side(alone, seconds, groups, list(persons))

    views = viewed(model, QUICK_MAPS if quick else MAPS, QUICK_MAP_SIZE if quick else MAP_SIZE)
    map_persons, maps, cameras = (list(each) for each in zip(*views))
    started = time.perf_counter()
    alone = [reconstruct(model, m, c, device=device).vertices for m, c in zip(maps, cameras)]
    seconds = (time.perf_counter() - started) / len(maps)
    pairs = list(zip(maps, cameras))
    groups = timed_groups(lambda group: [out.fit.vertices for out in reconstruct_many(
        model, [m for m, _ in group], [c for _, c in group], device=device)], pairs,
        QUICK_MAP_GROUPS if quick else MAP_GROUPS)
    render_rows = side_by_side(alone, seconds, groups, map_persons)

    embedded = load_model(default_model_path())
    _, points = people(embedded, 1)[0]
    counts = {fits: ops_per_iteration(embedded, points, fits, device) for fits in (1, 8)}
    _, normal_map, camera = viewed(embedded, 1, 256)[0]
    render_counts = {fits: render_ops_per_iteration(embedded, normal_map, camera, fits, device) for fits in (1, 8)}

    where = "one CPU thread" if device == "cpu" else device
    text = (f"{len(scans)} ICT scans (identity samples, one view, 4,300 points), the default pipeline on {where}; "
            "the fits one by one, then in groups fitted by `register_many` (each its own pose search and closed-form "
            "stage, the hybrid stage stepped together).\n\n" + "\n".join(table(rows)) + "\n\n"
            f"One iteration of the stage stepped together (paper `statistical`, embedded model): "
            f"{counts[1][0]:.1f} torch ops and {counts[1][1]:.2f} host waits for one fit, {counts[8][0]:.1f} and "
            f"{counts[8][1]:.2f} for 8 (launches per fit and iteration: {counts[8][0] / 8:.1f}).\n\n"
            f"{len(maps)} ICT normal maps ({maps[0].mask.shape[0]}², identity samples, yaw within ±30°), the render "
            f"default on {where}; the fits one by one, then in groups fitted by `reconstruct_many` (each its own "
            "alignment, the three stages stepped together: one renderer draws every fit into its own image).\n\n"
            + "\n".join(table(render_rows)) + "\n\n"
            f"One render iteration of the fits together (paper `statistical`, embedded model, 256²): "
            f"{render_counts[1][0]:.1f} torch ops and {render_counts[1][1]:.2f} host waits for one fit, "
            f"{render_counts[8][0]:.1f} and {render_counts[8][1]:.2f} for 8 (launches per fit and iteration: "
            f"{render_counts[8][0] / 8:.1f}).")
    return Section("together", "Many fits in one program", text,
                   data={"rows": rows, "ops": {str(k): v for k, v in counts.items()}, "render_rows": render_rows,
                         "render_ops": {str(k): v for k, v in render_counts.items()}})
