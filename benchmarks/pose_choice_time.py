"""What the pose search's choice among its refined poses costs (docs/studies.md §33): each of the
three refined poses is polished once (every mode, 1,500 points) so that a pose polishing 1.25×
better can overrule the refinement; for a model with a face, as ICT's, the kept pose's polish is
step 5's first pass, which the search ran before too, so the other two are the cost (a model without
a face pays all three). Measured in the same fits, on one thread: realistic
ICT scans (an identity sample, clutter 0.5, holes, noise, any pose, mm), the register default; each
polish timed as it runs. Prints each fit's seconds, the pose search's (``estimate_pose``), the two
extra polishes', and the whole fit's time without them ÷ with them; then medians.

    python benchmarks/pose_choice_time.py [--scans 3] [--rounds 3]
"""
from __future__ import annotations

import argparse
import statistics
import time
import warnings
from unittest import mock

import numpy as np
import torch

from cases import ict_model


def fit(model, scan) -> dict:
    """One default fit of ``scan`` (M, 3): seconds of the whole fit, the pose search and the lead
    polishes that the refinement's choice alone would not have run."""
    from statfit.registration.job import register
    from statfit.registration.pose import search

    refined, polished = [], []
    refine, polish, estimate = search.refine_with_first_modes, search.polish_pose, search.estimate_pose
    searched = []

    def refine_logged(*args, **kwargs):
        out = refine(*args, **kwargs)
        refined.append(out[1])
        return out

    def polish_timed(*args, **kwargs):
        started = time.perf_counter()
        out = polish(*args, **kwargs)
        polished.append((out[1], time.perf_counter() - started))
        return out

    def estimate_timed(*args, **kwargs):
        started = time.perf_counter()
        out = estimate(*args, **kwargs)
        searched.append(time.perf_counter() - started)
        return out

    with mock.patch.object(search, "refine_with_first_modes", refine_logged), \
            mock.patch.object(search, "polish_pose", polish_timed), \
            mock.patch("statfit.registration.prealign.estimate_pose", estimate_timed), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        started = time.perf_counter()
        register(model, scan, "default", threads=1)
        whole = time.perf_counter() - started
    leads = polished[:len(refined)]
    best = int(np.argmin(refined))
    other = int(np.argmin([score for score, _ in leads]))
    kept = other if leads[best][0] > search.POLISHED_SWITCH * leads[other][0] else best
    extra = sum(seconds for index, (_, seconds) in enumerate(leads) if index != kept)
    return {"whole": whole, "search": searched[0], "extra": extra, "ratio": whole / (whole - extra)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scans", type=int, default=3)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    from statfit.core.threads import flush_denormals_everywhere
    from statfit.synth.scanner import realistic_scan

    torch.set_num_threads(1)
    flush_denormals_everywhere()
    model = ict_model()
    scans = []
    for seed in range(args.scans):
        rng = np.random.default_rng(seed)
        scans.append(realistic_scan(model.sample(rng), model.faces, rng).vertices)
    fit(model, scans[0])        # warm-up
    rows = []
    for _ in range(args.rounds):
        for seed, scan in enumerate(scans):
            rows.append(fit(model, scan))
            row = rows[-1]
            print(f"scan {seed}: whole {row['whole']:5.2f} s, pose search {row['search']:5.2f} s, the two extra "
                  f"polishes {row['extra']:5.2f} s, whole ÷ whole without them {row['ratio']:.3f}", flush=True)
    median = lambda key: statistics.median(row[key] for row in rows)  # noqa: E731
    print(f"medians over {len(rows)} fits: whole {median('whole'):.2f} s, pose search {median('search'):.2f} s, "
          f"extra polishes {median('extra'):.2f} s, ratio {median('ratio'):.3f}")


if __name__ == "__main__":
    main()
