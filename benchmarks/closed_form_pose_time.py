"""What the closed form's own rigid motion costs (docs/studies.md §47): `register` (the default) of a
realistic one-view scan of a MakeHuman face model sample (2,983 vertices, mm; its modes fitted without
their rigid motion), with the pose given by its landmarks (so the pose search's time is not in it),
with ``POSE_STD`` 0 (as before §47) and as shipped, alternating ``--rounds`` times in one process
(:func:`common.alternate`), one torch thread. Prints each fit and the ratios of the medians of the
whole fit and of its Gauss–Newton stage.

    python benchmarks/closed_form_pose_time.py [--rounds 4]
"""
from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import alternate, median_ratio  # noqa: E402
from families import build_all, landmarked_model  # noqa: E402

NAME = "makehuman-face sample 0"


def sample_scan(_: str):
    """Sample 0 of the MakeHuman face model, its realistic scan and true landmarks (scan frame)."""
    from statfit.structures.scan import Scan
    from statfit.synth.scanner import realistic_scan

    build_all(["makehuman-face"], 1)
    model = landmarked_model("makehuman-face")
    shape = model.sample(np.random.default_rng(7000))
    made = realistic_scan(shape, model.faces, np.random.default_rng(3000), yaw_deg=20, clutter=0.0, units="mm")
    return model, Scan.from_mesh(made.vertices, made.faces), made.transform.apply(shape[model.landmarks])


def fit(case, pose_std: float) -> dict:
    """One default fit of the case with the closed form's rigid motion at ``pose_std``: its seconds."""
    import statfit.registration.posed as posed
    from statfit.registration.job import register

    model, scan, landmarks = case
    posed.POSE_STD = pose_std
    result = register(model, scan, landmarks=landmarks, threads=1)
    return {"fit": result.seconds, "closed": result.stage_seconds.get("gauss-newton", 0.0)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=4)
    args = parser.parse_args()
    import statfit.registration.posed as posed

    torch.set_num_threads(1)
    warnings.simplefilter("ignore")
    variants = (0.0, posed.POSE_STD)
    rows = alternate([NAME], sample_scan, variants, args.rounds, fit,
                     lambda pose_std, row: f"pose_std {pose_std:g}: fit {row['fit']:.3f} s, "
                                           f"Gauss-Newton {row['closed']:.3f} s", warm_up=True)
    print(f"{NAME}, the default with landmarks, one thread, {args.rounds} rounds: pose_std {variants[1]:g} ÷ 0, "
          f"medians: fit {median_ratio(rows, NAME, 'fit', variants[1], 0.0):.3f}, "
          f"Gauss-Newton {median_ratio(rows, NAME, 'closed', variants[1], 0.0):.3f}")


if __name__ == "__main__":
    main()
