"""The default render fit's time with the visibility refreshed every call and as shipped (reused for
``statfit.render.visibility.VISIBILITY_EVERY`` calls in the fit's stages; docs/studies.md §31), side
by side in one process on one thread: ICT's maps (benchmarks/cases.py) at one size, the two settings
alternating, ``--rounds`` times each. Prints, per fit, the whole fit's, the alignment's and the
loop's seconds, the loop's ms per iteration and the error; then the medians' ratios.

    python benchmarks/render_visibility_time.py [--size 512] [--rounds 2] [--cases jaw-open smile]
"""
from __future__ import annotations

import argparse
import time
from unittest import mock

import torch

from cases import ict_model, normal_case, relative_errors
from common import alternate, median_ratio


def fit(named, model, every_call: bool) -> dict:
    """One default fit of ``named``'s map: seconds (whole, alignment, loop), loop ms per iteration, error."""
    import statfit.render.visibility as visibility
    from statfit.render.job import reconstruct

    every = 1 if every_call else visibility.VISIBILITY_EVERY
    with mock.patch.object(visibility, "VISIBILITY_EVERY", every):
        started = time.perf_counter()
        result = reconstruct(model, named.normal_map, named.camera, "default", threads=1)
        whole = time.perf_counter() - started
    alignment = result.stage_seconds.get("alignment", 0.0)
    return {"whole": whole, "alignment": alignment, "loop": whole - alignment,
            "ms": 1000 * (whole - alignment) / result.iterations,
            "error": 100 * relative_errors(result.vertices, named.target, named.observed)["all"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--cases", nargs="*", default=["jaw-open", "smile"])
    args = parser.parse_args()
    torch.set_num_threads(1)
    model = ict_model()
    rows = alternate(args.cases, lambda case: normal_case(case, args.size), (True, False), args.rounds,
                     lambda named, every_call: fit(named, model, every_call),
                     lambda every_call, row: f"{'every call' if every_call else 'shipped':10s} whole "
                                             f"{row['whole']:6.1f} s, alignment {row['alignment']:5.1f} s, loop "
                                             f"{row['loop']:6.1f} s ({row['ms']:.1f} ms an iteration), error "
                                             f"{row['error']:.4f}")
    for case in args.cases:
        print(f"{case}: shipped ÷ every call, medians: whole {median_ratio(rows, case, 'whole', False, True):.3f}, "
              f"loop per iteration {median_ratio(rows, case, 'ms', False, True):.3f}")


if __name__ == "__main__":
    main()
