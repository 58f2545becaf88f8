"""A face-mask model's pose without landmarks (issue 37, part 1): realistic scans of the ICT mask
family's people, and of the MakeHuman face family's (a face mask cut from a body model, whose modes
are 99.9% rigid motion, fitted without it by the jobs' rule: a check family no default was chosen
on) (benchmarks/families.py: ICT's face geometry alone, decimated to ~3,000 vertices,
mm; a person is an ICT identity sample plus an expression the model lacks, cut the same way), seen by
the simulated range scanner (one view, yaw uniform in ±45°, 3 holes, depth noise; no clutter: a mask
has no head for hair to lie on), turned by a rotation uniform over all rotations, moved, and written
in mm, cm or m at random. Each scan is fitted with its family's model by ``pca`` without landmarks
(``--align auto``) and with its 51 inner landmarks (1 mm noise) placing the start only
(``--landmark-weight 0``: the two fits differ by their pose alone); the landmark error of each (mm,
against the person's true landmarks) and their ratio. Target: within 1.5× on ≥ 95% of the scans.
Issue 37 asks it of model-generated scans: the MakeHuman face model's own samples (coefficients
~ N(0, 1)) are a third case beside its held-out people, who lie outside it.

    python benchmarks/run.py --only mask_pose
"""
from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from common import Section

SCANS, QUICK_SCANS = 40, 4
FAMILIES = {"ict-mask": "ICT face-mask people, fitted with the ICT mask model (3,052 vertices, mm)",
            "makehuman-face": "MakeHuman face people (held-out bodies' faces), fitted with the MakeHuman face model "
                              "(2,983 vertices, mm; 99.9% of its modes rigid motion, fitted without it)"}
# Issue 37's target as written: scans of people the model itself generates (coefficients ~ N(0, 1)).
SAMPLED = {"makehuman-face": "the MakeHuman face model's own samples (model-generated: issue 37's target as "
                             "written), fitted with that model"}
METHOD = "pca"
INNER = slice(17, 68)
LANDMARK_NOISE_MM = 1.0
TARGET_RATIO = 1.5
UNITS = ("mm", "cm", "m")
MM_PER_UNIT = {"mm": 1.0, "cm": 10.0, "m": 1000.0}


def pose_case(family: str, seed: int, rigid_modes: str = "auto", sampled: bool = False) -> dict:
    """Person ``seed`` of ``family`` (``sampled``: a sample of the family's model instead) fitted
    without landmarks and with them placing the start."""
    import torch

    torch.set_num_threads(1)
    from families import landmarked_model, person, person_landmarks
    from statfit.core.threads import flush_denormals_everywhere
    from statfit.errors import StatfitError
    from statfit.registration.job import register
    from statfit.structures.scan import Scan
    from statfit.synth.scanner import realistic_scan

    flush_denormals_everywhere()
    model = landmarked_model(family)
    rng = np.random.default_rng(3000 + seed)
    units = UNITS[rng.integers(len(UNITS))]
    shape = model.sample(np.random.default_rng(7000 + seed)) if sampled else person(family, seed)
    made = realistic_scan(shape, model.faces, rng, yaw_deg=rng.uniform(-45, 45), clutter=0.0, units=units)
    scan = Scan.from_mesh(made.vertices, made.faces)
    truth = made.transform.apply(shape[model.landmarks] if sampled else person_landmarks(family, seed))
    inner = np.zeros(len(truth), dtype=bool)
    inner[INNER] = True
    noisy = truth + rng.normal(scale=LANDMARK_NOISE_MM / MM_PER_UNIT[units], size=truth.shape)
    given = np.where(inner[:, None], noisy, np.nan)

    def error(vertices: np.ndarray) -> float:
        return float(np.linalg.norm(vertices[model.landmarks[inner]] - truth[inner], axis=1).mean() * MM_PER_UNIT[units])

    placed = register(model, scan, METHOD, landmarks=given, landmark_weight=0.0, threads=1, rigid_modes=rigid_modes)
    row = {"seed": seed, "units": units, "placed_mm": error(placed.vertices)}
    try:
        without = register(model, scan, METHOD, threads=1, rigid_modes=rigid_modes)
    except StatfitError as refusal:     # the pose search refused the scan (its one line); it counts as a miss
        return row | {"refused": str(refusal)}
    return row | {"without_mm": error(without.vertices), "ambiguous": bool(without.pose["ambiguous"]),
                  "align_s": without.seconds}


def run(quick: bool, device: str, image_dir) -> Section:
    from families import build_all

    scans = QUICK_SCANS if quick else SCANS
    build_all(["ict", *FAMILIES], scans)
    cases = [(family, False, what) for family, what in FAMILIES.items()] + \
            [(family, True, what) for family, what in SAMPLED.items()]
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        rows = {(family, sampled): list(pool.map(pose_case, [family] * scans, range(scans), ["auto"] * scans,
                                                 [sampled] * scans)) for family, sampled, _ in cases}
    return Section("mask_pose", "A face-mask model's pose without landmarks",
                   "\n\n".join(_paragraph(what, rows[(family, sampled)]) for family, sampled, what in cases),
                   data={"rows": {family + (" samples" if sampled else ""): case_rows
                                  for (family, sampled), case_rows in rows.items()}})


def _paragraph(what: str, rows: list[dict]) -> str:
    fitted = [r for r in rows if "without_mm" in r]
    refused = [r for r in rows if "refused" in r]
    ratio = np.array([r["without_mm"] / r["placed_mm"] for r in fitted])
    within = int((ratio <= TARGET_RATIO).sum())
    beyond = [r for r in fitted if r["without_mm"] > TARGET_RATIO * r["placed_mm"]]
    text = (f"{len(rows)} realistic scans (any rotation, offset and unit; yaw within ±45°) of {what}, by `{METHOD}`. "
            f"Landmark error (51 inner landmarks, mm): without landmarks mean "
            f"{np.mean([r['without_mm'] for r in fitted]):.2f}, median "
            f"{np.median([r['without_mm'] for r in fitted]):.2f} (the {len(fitted)} fitted); with the landmarks "
            f"placing the start only mean {np.mean([r['placed_mm'] for r in rows]):.2f}. Within {TARGET_RATIO}× of it: "
            f"**{within} of {len(rows)}** ({100 * within / len(rows):.0f}%; target ≥ 95%). Ratio median "
            f"{np.median(ratio):.2f}, worst {ratio.max():.2f}. Said ambiguous: {sum(r['ambiguous'] for r in fitted)}.")
    if beyond:
        text += " Beyond: " + "; ".join(f"seed {r['seed']} ({r['without_mm']:.1f} vs {r['placed_mm']:.1f} mm)"
                                        for r in beyond) + "."
    if refused:
        text += (f" Refused without landmarks (the pose search's one line; fitted with them): {len(refused)}, seeds "
                 + ", ".join(str(r["seed"]) for r in refused) + ".")
    return text
