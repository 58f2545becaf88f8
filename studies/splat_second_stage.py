"""The splat default's second stage (docs/studies.md §14): after the same 300 statistical
iterations (β 1000, mode gain 1, lr 0.05), which second stage trades geometry for held-out images
best? Unfiltered vertices at three step sizes, Laplacian-filtered (smooth) vertices at three, or
the statistical filter at β 10 (off-model gain 1/11, 200 + 200 iterations). The four cases,
metrics and fits of ``study_splat.py``.

Results: ``studies/results/splat_second_stage.json`` (a rerun resumes); ``--report`` prints the table.
From the repository root:

    PYTHONPATH=. python studies/splat_second_stage.py [--variants a,b] [--report]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import study_splat  # noqa: E402

from statfit.core import methods  # noqa: E402
from statfit.core.settings import Settings  # noqa: E402

RESULTS = study_splat.ROOT / "studies" / "results" / "splat_second_stage.json"
SHAPE = Settings("statistical", 300, 0.05, beta=1000.0, mode_gain=1.0)
VARIANTS = {
    "unfiltered lr 0.0003": (SHAPE, Settings("none", 100, 0.0003)),
    "unfiltered lr 0.0006": (SHAPE, Settings("none", 100, 0.0006)),
    "unfiltered lr 0.001": (SHAPE, Settings("none", 100, 0.001)),
    "laplacian lr 0.003": (SHAPE, Settings("laplacian", 100, 0.003, lam=19.0)),
    "laplacian lr 0.01": (SHAPE, Settings("laplacian", 100, 0.01, lam=19.0)),
    "laplacian lr 0.03": (SHAPE, Settings("laplacian", 100, 0.03, lam=19.0)),
    "statistical beta 10": (Settings("statistical", 200, 0.05, beta=1000.0, mode_gain=1.0),
                            Settings("statistical", 200, 0.05, beta=10.0, mode_gain=1.0)),
}


def report(rows: list[dict], pca: dict[tuple[int, str], float]) -> str:
    lines = ["| second stage | cases | all % | held-out PSNR dB | PSNR over `pca` dB |", "|---|---|---|---|---|"]
    for name in VARIANTS:
        mine = [r for r in rows if r["variant"] == name]
        if mine:
            gain = np.mean([r["psnr"] - pca[(r["seed"], r["expression"])] for r in mine])
            lines.append(f"| {name} | {len(mine)} | {100 * np.mean([r['error_all'] for r in mine]):.2f} | "
                         f"{np.mean([r['psnr'] for r in mine]):.2f} | {gain:+.2f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--report", action="store_true")
    args = parser.parse_args()
    rows = json.loads(RESULTS.read_text()) if RESULTS.exists() else []
    pca = {(r["seed"], r["expression"]): r["psnr"] for r in study_splat.load() if r["method"] == "pca"}
    if not args.report:
        for name in args.variants.split(","):
            methods.PIPELINES["splat"]["default"] = methods.Pipeline(VARIANTS[name])
            for seed, expression in study_splat.CASES:
                if any(r["variant"] == name and r["seed"] == seed for r in rows):
                    continue
                row = {**study_splat.run_one((seed, expression, "default")), "variant": name}
                rows.append(row)
                RESULTS.write_text(json.dumps(rows, indent=1) + "\n")
                print(f"{name}: {seed} {expression} all {100 * row['error_all']:.2f}% PSNR {row['psnr']:.2f}",
                      flush=True)
    print(report(rows, pca))


if __name__ == "__main__":
    main()
