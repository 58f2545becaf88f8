"""What a model's ``face`` region does to a cluttered scan's fit (docs/formats.md, "What a `face` region does").

With clutter, register's data term keeps to the model's face: its ``face`` region where it has one, else
the vertices within half an RMS radius of a landmark (statfit.model.statmodel.face_triangles). ICT-FaceKit
names its whole face geometry (vertices 0–9408: forehead to scalp, ears) ``face``. This fits ICT people
scanned with 50% clutter (hair, neck, shoulders; mm, any pose; the default pipeline, one thread) with the
ICT model carrying four kinds of face:

- ``face geometry + 68 landmarks``: ICT's face geometry as ``region_face`` and its 68 landmarks (what a
  folder import with landmarks added gives);
- ``68 landmarks``: the 68 landmarks alone (what ``model import`` of the light npz gives, and since
  session 38 every command's ``--model``);
- ``51 inner landmarks``: Multi-PIE 17–67 alone (docs/benchmarks.md §8's model);
- ``neither``: the light npz as ``load_model`` (the contract's reader) reads it.

Score: mean distance (mm) of the fit's vertices within 3 cm of an inner landmark to the truth.

    python studies/face_region_clutter.py            # 4 people × 4 models, ~3 min on one core
    python studies/face_region_clutter.py --report   # the table of the stored rows
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ICT = ROOT.parent / "shared" / "data" / "ict-face" / "ict_face_identity.npz"
ROWS = ROOT / "studies" / "results" / "face_region_clutter.json"
SEEDS = (50, 51, 52, 53)
KINDS = ("face geometry + 68 landmarks", "68 landmarks", "51 inner landmarks", "neither")


def models() -> dict:
    from statfit.model.importers import import_model
    from statfit.model.statmodel import load_model, with_landmarks, with_regions

    plain = load_model(ICT)
    imported = import_model(ICT)            # landmarks68 → landmarks; the geometry as face_geometry
    landmarks = imported.landmarks
    return {KINDS[0]: with_regions(with_landmarks(plain, landmarks), {"face": imported.regions["face_geometry"]}),
            KINDS[1]: with_landmarks(plain, landmarks), KINDS[2]: with_landmarks(plain, landmarks[17:68]),
            KINDS[3]: plain}


def run() -> list[dict]:
    import torch

    from statfit.registration.job import register
    from statfit.structures.scan import Scan
    from statfit.synth.scanner import realistic_scan

    torch.set_num_threads(1)
    kinds = models()
    plain = kinds["neither"]
    inner = kinds["51 inner landmarks"].landmarks
    near = np.linalg.norm(plain.template[:, None] - plain.template[inner][None], axis=-1).min(axis=1) < 3.0
    rows = []
    for seed in SEEDS:
        shape = plain.sample(np.random.default_rng(seed))
        made = realistic_scan(shape, plain.faces, np.random.default_rng(seed), clutter=0.5, units="mm")
        scan = Scan.from_mesh(made.vertices, made.faces)
        for kind, model in kinds.items():
            fit = register(model, scan, "default", threads=1)
            rows.append({"seed": seed, "model": kind, "face_mm": float(np.linalg.norm(fit.vertices - made.truth,
                                                                                        axis=1)[near].mean()),
                         "seconds": fit.seconds})
            print(rows[-1], flush=True)
    return rows


def report(rows: list[dict]) -> str:
    lines = ["Face error (mm, vertices within 3 cm of an inner landmark) of the default fit of cluttered ICT "
             "scans, by the face the model carries.", "", "| model's face | " + " | ".join(f"seed {s}" for s in SEEDS)
             + " | mean |", "|---|" + "---|" * (len(SEEDS) + 1)]
    for kind in KINDS:
        values = [r["face_mm"] for s in SEEDS for r in rows if r["model"] == kind and r["seed"] == s]
        lines.append(f"| {kind} | " + " | ".join(f"{v:.3f}" for v in values) + f" | **{np.mean(values):.3f}** |")
    return "\n".join(lines)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--report", action="store_true", help="only print the table of the stored rows")
    if not parser.parse_args().report:
        ROWS.write_text(json.dumps(run(), indent=1))
    print(report(json.loads(ROWS.read_text())))
