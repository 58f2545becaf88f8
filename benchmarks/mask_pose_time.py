"""What scoring a face mask's poses from both sides costs (docs/studies.md §37): ``estimate_pose`` of
the ICT mask (3,052 vertices, mm) on a realistic scan of one of its people, with the search's score
from the scan's side alone (as before §37) and from both sides (as shipped), alternating ``--rounds``
times in one process, one torch thread. Prints the medians and their ratio.

    python benchmarks/mask_pose_time.py [--rounds 4]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
import warnings
from contextlib import nullcontext
from pathlib import Path
from unittest import mock

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from families import build_all, landmarked_model, person  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=4)
    args = parser.parse_args()
    torch.set_num_threads(1)
    from statfit.registration.pose import search
    from statfit.structures.scan import Scan
    from statfit.synth.scanner import realistic_scan

    build_all(["ict", "ict-mask"], 1)
    model = landmarked_model("ict-mask")
    made = realistic_scan(person("ict-mask", 0), model.faces, np.random.default_rng(3000), yaw_deg=20, clutter=0.0,
                          units="mm")
    scan = Scan.from_mesh(made.vertices, made.faces)
    warnings.simplefilter("ignore")
    search.estimate_pose(model, scan)      # warm: imports, the first KD-trees
    seconds: dict[str, list[float]] = {"scan's side": [], "both sides": []}
    for _ in range(args.rounds):
        for score in seconds:
            with mock.patch.object(search, "of_part_of_a_subject", lambda *_: False) if score == "scan's side" \
                    else nullcontext():
                start = time.perf_counter()
                search.estimate_pose(model, scan)
                seconds[score].append(time.perf_counter() - start)
    alone, both = (statistics.median(values) for values in seconds.values())
    print(f"estimate_pose, ICT mask, one thread, {args.rounds} rounds: the scan's side alone {alone:.3f} s, "
          f"both sides {both:.3f} s (medians); both ÷ alone {both / alone:.3f}")


if __name__ == "__main__":
    main()
