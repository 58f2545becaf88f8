"""Face-mask models under a real scan's clutter: what hair over a mask's forehead costs (issue 37,
part 1; docs/studies.md §34).

A face-mask model (the front of the face only, as BFM and most scanner-built models are) has no
scalp. A realistic scan's hair layer (:func:`statfit.synth.scanner.hair_layer`: the shape's top,
lifted by 5–9 mm) then lies over the mask's upper forehead, as a fringe would. Three masks cut from
this repository's heads (``statfit model cut --region face``): the cross-family studies' ICT mask
(3,000 vertices, mm; benchmarks/families.py), the embedded head's face (1,654 vertices) and that
face decimated to 500. People drawn
from each mask's own model (in its span: only the clutter is foreign), realistic scans in any pose
(mm), four ways: no clutter, hair only, neck and shoulders only, both (0.5 clutter points per face
point). Each scan fitted four ways, the pose found without landmarks:

- ``default``: as shipped (the fallback to ``laplacian`` where the fit needs an implausible code);
- ``default, no fallback``;
- ``laplacian`` and ``pca`` at their tuned settings.

Reported: the mean vertex error over the whole mask (mm), the pose's rotation error (°) and how
many of the default's fits fell back.

    python studies/mask_clutter.py            # ~6 min on 2 cores
    python studies/mask_clutter.py --report   # the tables from studies/results/mask_clutter.json
"""
from __future__ import annotations

import sys
from functools import lru_cache
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from study_runs import study_main  # noqa: E402  (beside this script)

RESULTS = ROOT / "studies" / "results" / "mask_clutter.json"
MODELS = {"ICT face mask (3,000 vertices, mm)": ("ict-mask", None), "embedded face": ("embedded", None),
          "embedded face, 500 vertices": ("embedded", 500)}
SCANS = {"no clutter": (0.0, ()), "hair": (0.5, ("hair",)), "neck": (0.5, ("neck",)),
         "hair and neck": (0.5, ("hair", "neck"))}
FITS = {"default": ("default", True), "default, no fallback": ("default", False), "laplacian": ("laplacian", True),
        "pca": ("pca", True)}
SEEDS = range(3)


@lru_cache(maxsize=None)
def mask(name: str):
    """The face-mask model ``name`` (of MODELS): the cross-family studies' ICT mask
    (benchmarks/families.py), or cut from the embedded head."""
    from families import family_model
    from statfit.model.cut import decimated, region_part

    family, vertices = MODELS[name]
    if family == "ict-mask":
        return family_model(family)
    face = region_part(family_model(family), "face")
    return face if vertices is None else decimated(face, vertices)


def made_scan(model_name: str, scan_name: str, seed: int):
    """The mask ``model_name`` and its realistic scan ``scan_name`` of person ``seed`` (module
    docstring): (model, statfit.synth.scanner's scan with its truth)."""
    import torch

    torch.set_num_threads(1)
    from statfit.core.threads import flush_denormals_everywhere
    from statfit.synth.scanner import realistic_scan

    flush_denormals_everywhere()
    model = mask(model_name)
    rng = np.random.default_rng(2000 + seed)
    clutter, parts = SCANS[scan_name]
    return model, realistic_scan(model.sample(rng), model.faces, rng, yaw_deg=float(rng.uniform(-30, 30)),
                                 clutter=clutter, clutter_parts=parts or ("hair", "neck"), units="mm")


def run_case(model_name: str, scan_name: str, seed: int) -> dict:
    from scipy.spatial.transform import Rotation
    from statfit.registration.job import register
    from statfit.structures.scan import Scan

    model, made = made_scan(model_name, scan_name, seed)
    scan = Scan.from_mesh(made.vertices, made.faces)
    row = {"model": model_name, "scan": scan_name, "seed": seed, "clutter_ratio": made.clutter_ratio}
    for label, (method, fallback) in FITS.items():
        fit = register(model, scan, method, fallback=fallback, threads=1)
        row[f"{label} mm"] = float(np.linalg.norm(fit.vertices - made.truth, axis=1).mean())
        if label == "default":
            row["fell back"] = bool(fit.fallback and fit.fallback.get("used"))
            row["pose deg"] = float(np.degrees(Rotation.from_matrix(
                fit.transform.rotation @ made.transform.rotation.T).magnitude()))
    return row


def report(rows: list[dict]) -> str:
    lines = ["| mask | scan | default mm | default, no fallback mm | laplacian mm | pca mm | fell back "
             "| pose ° (mean, max) |", "|---|---|---|---|---|---|---|---|"]
    for model_name in MODELS:
        for scan_name in SCANS:
            mine = [r for r in rows if r["model"] == model_name and r["scan"] == scan_name]
            if not mine:
                continue
            means = " | ".join(f"{np.mean([r[f'{label} mm'] for r in mine]):.2f}" for label in FITS)
            pose = np.array([r["pose deg"] for r in mine])
            lines.append(f"| {model_name} | {scan_name} | {means} | {sum(r['fell back'] for r in mine)} of "
                         f"{len(mine)} | {pose.mean():.1f}, {pose.max():.1f} |")
    return "\n".join(lines)


def runs() -> list[tuple]:
    return [(model_name, scan_name, seed) for model_name in MODELS for scan_name in SCANS for seed in SEEDS]


if __name__ == "__main__":
    study_main(__doc__, run_case, runs, RESULTS, report, key=lambda row: (row["model"], row["scan"], row["seed"]))
