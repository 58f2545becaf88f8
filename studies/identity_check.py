"""Same seed, same mesh: SHA-256 of every job's output for every method, to compare two revisions
bit for bit (the one-core redesign was checked this way; docs/studies.md §10 has the record).

    python studies/identity_check.py > before.txt   # on one revision
    python studies/identity_check.py > after.txt    # on another; then: diff before.txt after.txt

Short fits (so the whole check takes about two minutes on one thread): registration on the embedded
model and on the ICT head (jaw-open case), rendering of a 128² ICT normal map, and inpainting of a
generated 64² face texture; every method of each job.
"""
from __future__ import annotations

import hashlib
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

REGISTER = ("default", "statistical", "hybrid", "laplacian", "pca", "regularized", "none")
INPAINT = ("hybrid", "statistical", "laplacian", "pca", "none")


def digest(array: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(array, dtype=np.float64).tobytes()).hexdigest()[:16]


def main() -> None:
    from cases import ict_model, normal_case, scan_case
    from statfit.render.job import reconstruct
    from statfit.model.statmodel import default_model_path, load_model
    from statfit.registration.job import register
    from statfit.synth.sample import sample_target, scan_from_view
    from statfit.texture.inpaint import inpaint
    from statfit.texture.model import build_texture_model

    torch.set_num_threads(1)
    embedded = load_model(default_model_path())
    rng = np.random.default_rng(3)
    points = scan_from_view(sample_target(embedded, rng), embedded.faces, rng, 2000, 30.0)
    ict_scan = scan_case("jaw-open")
    for method in REGISTER:
        for name, model, scan in (("embedded", embedded, points), ("ict", ict_model(), ict_scan.points)):
            fit = register(model, scan, method, iterations=60, seed=0)
            print(f"register {name} {method} {digest(fit.vertices)}")
    normals = normal_case("jaw-open", 128)
    for method in REGISTER:
        fit = reconstruct(ict_model(), normals.normal_map, normals.camera, method, iterations=20, seed=0)
        print(f"render ict {method} {digest(fit.vertices)}")
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from texture_fixtures import brow_hole, face_textures
    textures = face_textures(41, 64, seed=0)
    texture_model = build_texture_model([(str(i), t) for i, t in enumerate(textures[1:])], (64, 64), 20)
    for method in INPAINT:
        filled = inpaint(textures[0], brow_hole(64), method, texture_model if method != "laplacian" else None)
        print(f"inpaint face {method} {digest(filled.result)}")


if __name__ == "__main__":
    main()
