"""What the register fallback gate's border band costs: the residual's distances with and without it.

    python benchmarks/gate_border_time.py [--rounds 10]

The gate measures, once per fit, the distance of the scan points to the fitted surface
(:func:`statfit.geometry.metrics.inside_distance`); since docs/studies.md §35 it also leaves out the
points near the model's open border (``FALLBACK_BORDER_BAND``). Here: the ICT head (open at the neck)
in its unit frame and 4,300 points scattered about its surface, one torch thread, the two calls
alternating ``--rounds`` times in one process. Prints the medians and their ratio.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ICT_MODEL  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=10)
    args = parser.parse_args()
    torch.set_num_threads(1)
    from statfit.core.methods import FALLBACK_BORDER_BAND
    from statfit.geometry.metrics import inside_distance
    from statfit.model.statmodel import load_model

    model = load_model(ICT_MODEL)
    vertices = model.frame.to_unit(model.template)
    rng = np.random.default_rng(0)
    points = vertices[rng.choice(len(vertices), 4300)] + rng.normal(scale=0.01, size=(4300, 3))
    seconds: dict[float, list[float]] = {0.0: [], FALLBACK_BORDER_BAND: []}
    for _ in range(args.rounds):
        for band in seconds:
            start = time.perf_counter()
            inside_distance(points, vertices, model.faces, border_band=band)
            seconds[band].append(time.perf_counter() - start)
    without, with_band = (statistics.median(values) for values in seconds.values())
    print(f"inside_distance, ICT, 4,300 points, one thread, {args.rounds} rounds: without the band "
          f"{without * 1e3:.1f} ms, with it {with_band * 1e3:.1f} ms (medians); with ÷ without {with_band / without:.3f}")


if __name__ == "__main__":
    main()
