"""A face-mask model's pose without landmarks (issue 37, part 1): realistic scans of the ICT mask
family's people (benchmarks/families.py: ICT's face geometry alone, decimated to ~3,000 vertices,
mm; a person is an ICT identity sample plus an expression the model lacks, cut the same way), seen by
the simulated range scanner (one view, yaw uniform in ±45°, 3 holes, depth noise; no clutter: a mask
has no head for hair to lie on), turned by a rotation uniform over all rotations, moved, and written
in mm, cm or m at random. Each scan is fitted with the mask model by ``pca`` without landmarks
(``--align auto``) and with its 51 inner landmarks (1 mm noise) placing the start only
(``--landmark-weight 0``: the two fits differ by their pose alone); the landmark error of each (mm,
against the person's true landmarks) and their ratio. Target: within 1.5× on ≥ 95% of the scans.

    python benchmarks/run.py --only mask_pose
"""
from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from common import Section

SCANS, QUICK_SCANS = 40, 4
METHOD = "pca"
INNER = slice(17, 68)
LANDMARK_NOISE_MM = 1.0
TARGET_RATIO = 1.5
UNITS = ("mm", "cm", "m")
MM_PER_UNIT = {"mm": 1.0, "cm": 10.0, "m": 1000.0}


def pose_case(seed: int) -> dict:
    import torch

    torch.set_num_threads(1)
    from families import landmarked_model, person, person_landmarks
    from statfit.core.threads import flush_denormals_everywhere
    from statfit.registration.job import register
    from statfit.structures.scan import Scan
    from statfit.synth.scanner import realistic_scan

    flush_denormals_everywhere()
    model = landmarked_model("ict-mask")
    rng = np.random.default_rng(3000 + seed)
    units = UNITS[rng.integers(len(UNITS))]
    made = realistic_scan(person("ict-mask", seed), model.faces, rng, yaw_deg=rng.uniform(-45, 45), clutter=0.0,
                          units=units)
    scan = Scan.from_mesh(made.vertices, made.faces)
    truth = made.transform.apply(person_landmarks("ict-mask", seed))
    inner = np.zeros(len(truth), dtype=bool)
    inner[INNER] = True
    noisy = truth + rng.normal(scale=LANDMARK_NOISE_MM / MM_PER_UNIT[units], size=truth.shape)
    given = np.where(inner[:, None], noisy, np.nan)

    def error(vertices: np.ndarray) -> float:
        return float(np.linalg.norm(vertices[model.landmarks[inner]] - truth[inner], axis=1).mean() * MM_PER_UNIT[units])

    without = register(model, scan, METHOD, threads=1)
    placed = register(model, scan, METHOD, landmarks=given, landmark_weight=0.0, threads=1)
    return {"seed": seed, "units": units, "without_mm": error(without.vertices), "placed_mm": error(placed.vertices),
            "ambiguous": bool(without.pose["ambiguous"]), "align_s": without.seconds}


def run(quick: bool, device: str, image_dir) -> Section:
    from families import build_all

    scans = QUICK_SCANS if quick else SCANS
    build_all(["ict", "ict-mask"], scans)
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        rows = list(pool.map(pose_case, range(scans)))
    ratio = np.array([r["without_mm"] / r["placed_mm"] for r in rows])
    within = int((ratio <= TARGET_RATIO).sum())
    beyond = [r for r in rows if r["without_mm"] > TARGET_RATIO * r["placed_mm"]]
    text = (f"{len(rows)} realistic scans of ICT face-mask people (any rotation, offset and unit; yaw within ±45°), "
            f"fitted with the ICT mask model (3,052 vertices, mm) by `{METHOD}`. Landmark error (51 inner landmarks, "
            f"mm): without landmarks mean {np.mean([r['without_mm'] for r in rows]):.2f}, median "
            f"{np.median([r['without_mm'] for r in rows]):.2f}; with the landmarks placing the start only mean "
            f"{np.mean([r['placed_mm'] for r in rows]):.2f}. Within {TARGET_RATIO}× of it: **{within} of {len(rows)}** "
            f"({100 * within / len(rows):.0f}%; target ≥ 95%). Ratio median {np.median(ratio):.2f}, worst "
            f"{ratio.max():.2f}. Said ambiguous: {sum(r['ambiguous'] for r in rows)}."
            + ("" if not beyond else " Beyond: " + "; ".join(
                f"seed {r['seed']} ({r['without_mm']:.1f} vs {r['placed_mm']:.1f} mm)" for r in beyond) + "."))
    return Section("mask_pose", "A face-mask model's pose without landmarks", text, data={"rows": rows})
