"""The register default's time with its closed form ending at the last level (before docs/studies.md
§32) and as shipped (the level of its last two that best predicts the scan's edge), side by side in
one process on one thread: ICT's scan cases (benchmarks/cases.py), the two settings alternating,
``--rounds`` times each. Prints each fit's seconds, its closed form's seconds and the error (cm);
then the medians' ratios.

    python benchmarks/register_level_time.py [--rounds 4] [--cases jaw-open smile brow-up]
"""
from __future__ import annotations

import argparse
import time
from dataclasses import replace
from unittest import mock

import numpy as np
import torch

from cases import ict_model, scan_case
from common import alternate, median_ratio


def fit(named, model, last_level: bool) -> dict:
    """One default fit of ``named``'s scan: seconds (whole, closed form) and the all-vertex error (cm)."""
    from statfit.core.methods import PIPELINES
    from statfit.registration.job import register

    pipeline = PIPELINES["register"]["default"]
    if last_level:
        pipeline = replace(pipeline, stages=(replace(pipeline.stages[0], choose_levels=0), *pipeline.stages[1:]))
    with mock.patch.dict(PIPELINES["register"], {"default": pipeline}):
        started = time.perf_counter()
        result = register(model, named.points, "default", threads=1)
        whole = time.perf_counter() - started
    return {"whole": whole, "closed": result.stage_seconds.get("gauss-newton", 0.0),
            "error": float(np.linalg.norm(result.vertices - named.target, axis=1).mean())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--cases", nargs="*", default=["jaw-open", "smile", "brow-up"])
    args = parser.parse_args()
    from statfit.core.threads import flush_denormals_everywhere

    torch.set_num_threads(1)
    flush_denormals_everywhere()
    model = ict_model()
    rows = alternate(args.cases, scan_case, (True, False), args.rounds, lambda named, last: fit(named, model, last),
                     lambda last, row: f"{'last level' if last else 'shipped':10s} whole {row['whole']:5.2f} s, "
                                       f"closed form {row['closed']:5.2f} s, error {row['error']:.4f} cm", warm_up=True)
    for case in args.cases:
        print(f"{case}: shipped ÷ last level, medians: whole {median_ratio(rows, case, 'whole', False, True):.3f}, "
              f"closed form {median_ratio(rows, case, 'closed', False, True):.3f}")


if __name__ == "__main__":
    main()
