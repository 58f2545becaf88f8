"""What reading the light ICT-FaceKit npz's landmarks and face geometry changes: the register default
on ICT's people with ``--model ict_face_identity.npz`` as every command now reads it
(``open_model``: the 68 landmarks and the region ``face_geometry``) and as the contract's reader alone
reads it (``load_model``: neither; what every command read before, docs/studies.md §42).

Without landmarks or a face region the pose search has no face pass and the fit no hair rules: a
cluttered scan's hair, neck and shoulders pull on the whole head. Scans: realistic scans
(benchmarks/families.py; one view, yaw within ±40°, any rotation and offset, mm, 4,300 points on the
person, clutter 0, 0.5 and 2 per person point) of ICT's people, seeds 0–9. Each row keeps each
reading's mean vertex error over the head and over the face geometry (mm), or the refusal.

Nothing here was tuned: both readings run the shipped default.

    python studies/light_keys.py [--report]

~6 min on 2 cores; rows in studies/results/light_keys.json.
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "studies"))

from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "light_keys.json"
SEEDS, CLUTTER = 10, (0.0, 0.5, 2.0)
READINGS = ("contract only", "light keys")


def run_case(seed: int, clutter: float) -> dict:
    import warnings

    import numpy as np
    import torch
    from common import ICT_MODEL
    from families import family_model, person

    from statfit.errors import StatfitError
    from statfit.model.importers.cache import open_model
    from statfit.model.statmodel import load_model
    from statfit.registration.job import register
    from statfit.structures.scan import Scan
    from statfit.synth.scanner import realistic_scan

    torch.set_num_threads(1)
    models = {"contract only": load_model(ICT_MODEL), "light keys": open_model(ICT_MODEL)}
    face = models["light keys"].regions["face_geometry"]
    rng = np.random.default_rng(seed)
    made = realistic_scan(person("ict", seed), family_model("ict").faces, rng, 4300, yaw_deg=rng.uniform(-40, 40),
                          clutter=clutter, units="mm", posed=True)
    scan = Scan.from_mesh(made.vertices, made.faces)
    row = {"seed": seed, "clutter": clutter}
    for reading, model in models.items():
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                error = np.linalg.norm(register(model, scan, threads=1).vertices - made.truth, axis=1)
        except StatfitError as refused:
            row[f"refused_{reading}"] = str(refused)
            continue
        row[f"head_mm_{reading}"], row[f"face_mm_{reading}"] = float(error.mean()), float(error[face].mean())
    return row


def runs() -> list[tuple]:
    return [(seed, clutter) for clutter in CLUTTER for seed in range(SEEDS)]


def report(rows: list[dict]) -> str:
    import numpy as np

    lines = ["ICT's people (seeds 0–" + str(SEEDS - 1) + "), the register default with ICT's light npz read two ways: "
             "mean vertex error, mm (mean / largest over the people fitted both ways), on the head and on the face "
             "geometry; people refused; fits worse / better by more than 5% with the light keys", "",
             "| clutter | people | " + " | ".join(f"head, {r}" for r in READINGS) + " | "
             + " | ".join(f"face, {r}" for r in READINGS) + " | refused | face worse / better |",
             "|---|---|---|---|---|---|---|---|"]
    for clutter in CLUTTER:
        mine = [r for r in rows if r["clutter"] == clutter]
        both = [r for r in mine if all(f"head_mm_{reading}" in r for reading in READINGS)]
        cells = [f"{np.mean([r[f'{part}_mm_{reading}'] for r in both]):.2f} / "
                 f"{max(r[f'{part}_mm_{reading}'] for r in both):.2f}" for part in ("head", "face") for reading in READINGS]
        refused = " → ".join(str(sum(f"refused_{reading}" in r for r in mine)) for reading in READINGS)
        worse = sum(r["face_mm_light keys"] > 1.05 * r["face_mm_contract only"] for r in both)
        better = sum(r["face_mm_light keys"] < r["face_mm_contract only"] / 1.05 for r in both)
        lines.append(f"| {clutter} | {len(both)} | " + " | ".join(cells) + f" | {refused} | {worse} / {better} |")
    return "\n".join(lines)


if __name__ == "__main__":
    study_main(__doc__, run_case, runs, RESULTS, report, key=lambda row: (row["seed"], row["clutter"]))
