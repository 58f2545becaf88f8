"""Study behind the ``statfit inpaint`` defaults: a small sweep of step size, β, λ, iterations and
the starting point on the generated face textures (tests/texture_fixtures.py), and the digits check.

Faces: a PCA model (K = 40) of 150 generated 64×64 textures (seed 1); 8 held-out textures (seed 99)
with the hole of ``brow_hole`` (16% of the pixels, over the left eyebrow and eye). Digits: the 8×8
scikit-learn digits upscaled to 32×32, model (K = 30) of all but 20 held-out digits, hole = the
central 16×16 block. Metrics: RMS error and correlation on the hole pixels (tests/texture_fixtures.py),
mean over the held-out images. Writes ``studies/results/study_inpaint.json``; prints Markdown.

    OMP_NUM_THREADS=1 PYTHONPATH=. python studies/study_inpaint.py
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from statfit.texture.inpaint import inpaint, inpaint_settings
from statfit.texture.model import build_texture_model

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from texture_fixtures import brow_hole, face_textures, hole_errors  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "study_inpaint.json"


def faces_case():
    model = build_texture_model([(str(i), t) for i, t in enumerate(face_textures(150, 64, seed=1))], (64, 64), 40)
    return model, face_textures(8, 64, seed=99), brow_hole(64)


def digits_case():
    from sklearn.datasets import load_digits

    from statfit.texture.resample import resize_image

    digits = load_digits().images[..., None].astype(np.float32) / 16.0
    images = np.stack([resize_image(d, (32, 32)) for d in digits])
    model = build_texture_model([(str(i), d) for i, d in enumerate(images[20:])], (32, 32), 30)
    visible = np.ones((32, 32), bool)
    visible[8:24, 8:24] = False
    return model, images[:20], visible


def evaluate(case, method, start="mean", **overrides) -> dict:
    model, tests, visible = case
    settings = inpaint_settings(method, **overrides)
    use_model = model if method in ("hybrid", "statistical", "pca") else None
    scores, started = [], time.perf_counter()
    for truth in tests:
        if start == "mean-filled":   # the input with its holes filled by the model mean, no fit
            result = np.where(visible[..., None], truth, model.mean.reshape(truth.shape))
        else:
            result = inpaint(truth, visible, method, use_model, settings=settings, start=start).result
        scores.append(hole_errors(result, truth, visible))
    return {"method": method, "start": start if use_model else "visible mean",
            **{k: v for k, v in settings.describe().items() if k in ("iterations", "lr", "beta", "lam")},
            "rmse": float(np.mean([s["rmse"] for s in scores])),
            "correlation": float(np.mean([s["correlation"] for s in scores])),
            "seconds_per_fit": (time.perf_counter() - started) / len(tests)}


def main() -> None:
    torch.set_num_threads(1)
    rows = []
    faces, digits = faces_case(), digits_case()
    for start in ("mean", "reconstruction"):
        for lr in (0.003, 0.01, 0.03):
            for iterations in (100, 300, 1000):
                rows.append({"case": "faces", **evaluate(faces, "hybrid", start, lr=lr, iterations=iterations)})
    for beta in (10.0, 30.0, 100.0):
        for lam in (19.0, 99.0):
            rows.append({"case": "faces", **evaluate(faces, "hybrid", beta=beta, lam=lam)})
    for beta in (10.0, 30.0, 100.0):
        rows.append({"case": "faces", **evaluate(faces, "statistical", beta=beta)})
    for lr in (0.003, 0.01, 0.05, 0.2):
        rows.append({"case": "faces", **evaluate(faces, "pca", lr=lr)})
    for lr in (0.003, 0.01, 0.03, 0.1):
        for lam in (19.0, 99.0, 999.0):
            rows.append({"case": "faces", **evaluate(faces, "laplacian", lr=lr, lam=lam)})
    rows.append({"case": "faces", **evaluate(faces, "none")})
    rows.append({"case": "faces", **evaluate(faces, "hybrid", start="mean-filled")})
    for start in ("mean", "reconstruction"):
        for method in ("hybrid", "statistical", "pca"):
            rows.append({"case": "digits", **evaluate(digits, method, start)})
    for beta in (10.0, 100.0):
        rows.append({"case": "digits", **evaluate(digits, "hybrid", beta=beta)})
    rows.append({"case": "digits", **evaluate(digits, "pca", lr=0.05)})
    for lam in (19.0, 99.0, 999.0):
        rows.append({"case": "digits", **evaluate(digits, "laplacian", lam=lam)})
    rows.append({"case": "digits", **evaluate(digits, "none")})
    RESULTS.write_text(json.dumps(rows, indent=1) + "\n")
    columns = ("case", "method", "start", "iterations", "lr", "beta", "lam", "rmse", "correlation", "seconds_per_fit")
    print("| " + " | ".join(columns) + " |\n" + "|---" * len(columns) + "|")
    for r in rows:
        print("| " + " | ".join(f"{r[c]:.4g}" if isinstance(r[c], float) else str(r[c]) for c in columns) + " |")


if __name__ == "__main__":
    main()
