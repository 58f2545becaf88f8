"""What the closed form's own rigid motion costs (docs/studies.md §47): `register` (`pca`, the
default) of a realistic one-view scan of a MakeHuman face model sample (2,983 vertices, mm; its modes
fitted without their rigid motion), with the pose given by its landmarks (so the pose search's time
is not in it), with ``POSE_STD`` 0 (as before §47) and as shipped, alternating ``--rounds`` times in
one process, one torch thread. Prints the medians of the whole fit and of its Gauss–Newton stage.

    python benchmarks/closed_form_pose_time.py [--rounds 4]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import warnings
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from families import build_all, landmarked_model  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=4)
    args = parser.parse_args()
    torch.set_num_threads(1)
    import statfit.registration.posed as posed
    from statfit.registration.job import register
    from statfit.structures.scan import Scan
    from statfit.synth.scanner import realistic_scan

    build_all(["makehuman-face"], 1)
    model = landmarked_model("makehuman-face")
    rng = np.random.default_rng(3000)
    shape = model.sample(np.random.default_rng(7000))
    made = realistic_scan(shape, model.faces, rng, yaw_deg=20, clutter=0.0, units="mm")
    scan = Scan.from_mesh(made.vertices, made.faces)
    landmarks = made.transform.apply(shape[model.landmarks])
    shipped = posed.POSE_STD
    warnings.simplefilter("ignore")
    register(model, scan, landmarks=landmarks, threads=1)      # warm: imports, the first KD-trees
    seconds: dict[float, dict[str, list[float]]] = {0.0: {"fit": [], "gn": []}, shipped: {"fit": [], "gn": []}}
    for _ in range(args.rounds):
        for pose_std, times in seconds.items():
            posed.POSE_STD = pose_std
            fit = register(model, scan, landmarks=landmarks, threads=1)
            times["fit"].append(fit.seconds)
            times["gn"].append(fit.stage_seconds.get("gauss-newton", 0.0))
    before, now = ({k: statistics.median(v) for k, v in times.items()} for times in seconds.values())
    print(f"register (default, landmarks), MakeHuman face sample, one thread, {args.rounds} rounds (medians): "
          f"pose_std 0: fit {before['fit']:.3f} s, Gauss-Newton {before['gn']:.3f} s; pose_std {shipped:g}: fit "
          f"{now['fit']:.3f} s, Gauss-Newton {now['gn']:.3f} s; ratios {now['fit'] / before['fit']:.3f}, "
          f"{now['gn'] / before['gn']:.3f}")


if __name__ == "__main__":
    main()
