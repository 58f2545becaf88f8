"""Many scans registered in one program (issue 38, part 3): ``register_many`` against one ``register``
after another, side by side in one run.

ICT scans of 16 people (identity samples, one view each, yaw within ±40°, 4,300 points), the default
pipeline, one thread: seconds per fit one by one and with 4, 8 and 16 fits stepped together; each
fit's mean vertex error against the person (mm), and how far the fits together lie from the fits
alone (mm, per vertex). Then the torch ops and host waits of one iteration of the stage stepped
together (paper ``statistical``, the embedded model, ``align="none"``, counted as
``../shared/tools/sync_count.py`` counts them) for 1 and for 8 fits: what a GPU pays per launch.

    python benchmarks/run.py --only together [--device cuda]
"""
from __future__ import annotations

import time

import numpy as np

from common import ICT_MODEL, Section

PEOPLE, QUICK_PEOPLE = 16, 4
GROUPS, QUICK_GROUPS = (4, 8, 16), (2, 4)
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


def ops_per_iteration(model, points: np.ndarray, fits: int, device: str) -> tuple[float, float]:
    """(ops, host waits) per iteration of ``fits`` paper-statistical fits stepped together."""
    from gpu import per_iteration
    from statfit.registration.many import register_many

    return per_iteration(lambda it: register_many(model, [points] * fits, "statistical", preset="paper",
                                                  align="none", device=device, iterations=it)[0].fit.iterations)


def run(quick: bool, device: str, image_dir) -> Section:
    import torch

    from statfit.model.statmodel import default_model_path, load_model
    from statfit.registration.job import register
    from statfit.registration.many import register_many

    torch.set_num_threads(1)
    model = load_model(ICT_MODEL)
    cases = people(model, QUICK_PEOPLE if quick else PEOPLE)
    persons, scans = zip(*cases)
    register(model, scans[0], device=device)          # warm-up: caches, a GPU's start

    def error_mm(vertices: list[np.ndarray]) -> float:
        return float(np.mean([np.linalg.norm(v - p, axis=1).mean() for v, p in zip(vertices, persons)]) * MM_PER_UNIT)

    started = time.perf_counter()
    alone = [register(model, scan, device=device).vertices for scan in scans]
    rows = [{"together": 1, "s_per_fit": (time.perf_counter() - started) / len(scans), "error_mm": error_mm(alone),
             "from_alone_mm": 0.0}]
    for size in QUICK_GROUPS if quick else GROUPS:
        started = time.perf_counter()
        fits = [out.fit.vertices for first in range(0, len(scans), size)
                for out in register_many(model, list(scans[first:first + size]), device=device)]
        seconds = (time.perf_counter() - started) / len(scans)
        apart = np.median([np.linalg.norm(a - b, axis=1).mean() for a, b in zip(fits, alone)]) * MM_PER_UNIT
        rows.append({"together": size, "s_per_fit": seconds, "error_mm": error_mm(fits), "from_alone_mm": float(apart)})
    embedded = load_model(default_model_path())
    _, points = people(embedded, 1)[0]
    counts = {fits: ops_per_iteration(embedded, points, fits, device) for fits in (1, 8)}

    lines = ["| fits together | s per fit | × one by one | mean vertex error (mm) | median distance from the fit "
             "alone (mm) |", "|---|---|---|---|---|"]
    for row in rows:
        lines.append(f"| {row['together']} | {row['s_per_fit']:.2f} | {row['s_per_fit'] / rows[0]['s_per_fit']:.2f} | "
                     f"{row['error_mm']:.4f} | {row['from_alone_mm']:.4f} |")
    text = (f"{len(scans)} ICT scans (identity samples, one view, 4,300 points), the default pipeline on "
            f"{'one CPU thread' if device == 'cpu' else device}; the fits one by one, then in groups fitted by "
            "`register_many` (each its own pose search and closed-form stage, the hybrid stage stepped together).\n\n"
            + "\n".join(lines) + "\n\n"
            f"One iteration of the stage stepped together (paper `statistical`, embedded model): "
            f"{counts[1][0]:.1f} torch ops and {counts[1][1]:.2f} host waits for one fit, {counts[8][0]:.1f} and "
            f"{counts[8][1]:.2f} for 8 (launches per fit and iteration: {counts[8][0] / 8:.1f}).")
    return Section("together", "Many scans in one program", text,
                   data={"rows": rows, "ops": {str(k): v for k, v in counts.items()}})
