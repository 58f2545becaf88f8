"""Landmarks kept as a fit term (docs/studies.md §12): the fitted landmarks' error with the
landmarks used for the start only (weight 0) against a landmark term of weight 0.1, 1 and 10.

Off-span, as a real person is: the fit uses the ICT model's first 30 modes, the targets are drawn
from all 100 plus an expression outside the model (the four first registration study cases). The
scan and its 51 inner landmarks (Multi-PIE 17–67, 1 mm noise) are moved by a random rotation,
offset and a change to millimetres; one landmark (the nose tip) is misplaced by 20 mm. Errors in
mm against the true landmark positions (all 51) and all vertices.

    python studies/landmark_term.py        # ~6 min on 2 cores; writes studies/results/landmark_term.json
    python studies/landmark_term.py --methods default "closed form σ 0.003 → laplacian λ 300 lr 0.03 300 it" \
        --weights 10 --results studies/results/landmark_term_2026-11-26.json    # §19's check
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from cases import FORMER_DEFAULT  # noqa: E402

CASES = ("jaw-open", "smile", "brow-up", "cheek-puff")
WEIGHTS = (0.0, 0.1, 1.0, 10.0, 100.0)
METHODS = ("default", FORMER_DEFAULT, "pca")
MODES = 30
INNER = slice(17, 68)
NOSE_TIP = 30 - 17  # Multi-PIE 30, among the inner 51
MISPLACED_MM = 20.0
NOISE_MM = 1.0


def random_similarity(rng: np.random.Generator) -> tuple[np.ndarray, float, np.ndarray]:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    rotation = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    return rotation, 10.0, rng.uniform(-500, 500, size=3)  # ICT is in cm: ×10 = mm


def case_data(case: str) -> dict:
    """The case's model (ICT's first MODES modes, the inner landmarks), its scan moved by a random
    similarity into millimetres, the noisy landmarks (the nose tip misplaced), the moved truth."""
    from cases import ICT_MODEL, ict_model, scan_case
    from statfit.model.statmodel import with_landmarks

    indices = np.load(ICT_MODEL)["landmarks68"][INNER].astype(np.int64)
    model = with_landmarks(ict_model(), indices).truncated(MODES)
    data = scan_case(case)
    rng = np.random.default_rng(CASES.index(case))
    rotation, scale, offset = random_similarity(rng)
    move = lambda p: scale * p @ rotation.T + offset  # noqa: E731
    truth = move(data.target)
    landmarks = truth[indices] + rng.normal(scale=NOISE_MM, size=(len(indices), 3))
    direction = rng.normal(size=3)
    landmarks[NOSE_TIP] += MISPLACED_MM * direction / np.linalg.norm(direction)
    return {"model": model, "points": move(data.points), "landmarks": landmarks, "truth": truth, "indices": indices}


def fit(case: str, method: str, weight: float) -> dict:
    import torch

    torch.set_num_threads(1)
    from cases import register_named
    from statfit.core.threads import flush_denormals_everywhere

    flush_denormals_everywhere()
    data = case_data(case)
    model, indices, truth = data["model"], data["indices"], data["truth"]
    from default_candidates import candidates, register_candidate

    options = dict(landmarks=data["landmarks"], landmark_weight=weight, threads=1)
    result = (register_candidate(method, model, data["points"], **options) if method in candidates()
              else register_named(model, data["points"], method, **options))
    return {"case": case, "method": method, "weight": weight, "seconds": result.seconds,
            "landmark_mm": float(np.linalg.norm(result.vertices[indices] - truth[indices], axis=1).mean()),
            "all_mm": float(np.linalg.norm(result.vertices - truth, axis=1).mean())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--methods", nargs="*", default=list(METHODS),
                        help="methods, pipelines or candidates (studies/default_candidates.py)")
    parser.add_argument("--weights", nargs="*", type=float, default=list(WEIGHTS))
    parser.add_argument("--results", type=Path, default=ROOT / "studies" / "results" / "landmark_term.json")
    args = parser.parse_args()
    out = args.results
    done = json.loads(out.read_text()) if out.is_file() else []  # rerun: only what is missing
    have = {(r["case"], r["method"], r["weight"]) for r in done}
    runs = [(c, m, w) for m in args.methods for w in args.weights for c in CASES if (c, m, w) not in have]
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        rows = done + (list(pool.map(fit, *zip(*runs))) if runs else [])
    out.write_text(json.dumps(rows, indent=1))
    print("| method | landmark weight | " + " | ".join(CASES) + " | mean landmark mm | mean all-vertex mm | s |")
    print("|---|---|" + "---|" * (len(CASES) + 3))
    for method in args.methods:
        for weight in args.weights:
            cells = [r for r in rows if r["method"] == method and r["weight"] == weight]
            by_case = {r["case"]: r for r in cells}
            print(f"| {method} | {weight:g} | " + " | ".join(f"{by_case[c]['landmark_mm']:.2f}" for c in CASES)
                  + f" | {np.mean([r['landmark_mm'] for r in cells]):.2f} | {np.mean([r['all_mm'] for r in cells]):.2f}"
                  f" | {np.mean([r['seconds'] for r in cells]):.1f} |")


if __name__ == "__main__":
    main()
