"""A face mask's pose on a scan of a whole head (issue 37, part 1; docs/studies.md §37; measured, not
shipped).

The users issue 37 names bring a face-mask model (BFM's shape) and a scanner that sees the head. A
fuzz of the CLI (§37) found the embedded head's face cut (``statfit model cut --region face``)
refused on plain side scans of the embedded head itself: "the scan does not look like the model's
shape". Here: people of the embedded head (``synth scan``'s: a model sample, 4,300 points seen from
yaw 30°), each scan turned by a random rotation and moved (so the search cannot keep the scan where
it lies), the face cut's pose searched without landmarks (``estimate_pose``). The truth is the
scan's own pose: the cut keeps the head's vertex positions. Variants (the first two with the search's score before §37, the scan's side alone):

- ``before``: the 60 rotations placed with the model's side facing the scanner on the scan's
  centroid, scored by how much of the scan the model explains;
- ``front``: those, and the same 60 placed on the front of the scan instead (the mean of the 20% of
  points nearest the scanner along its mean normal): a mask belongs on the face, not on the middle
  of a head;
- ``shipped``: the starts of ``before``, each pose scored (the screening's and the candidates'
  choice) from both sides: that score averaged with the model's, every model vertex that faces the
  scanner at its distance to the scan (capped as the score caps a scan point's), every other vertex
  at the cap (``statfit.registration.pose.scoring.unsupported_share``). A mask lying on the back of
  the head then pays for its face, which nothing supports.

    python studies/mask_on_head.py              # 60 searches, ~3 min on 2 cores
    python studies/mask_on_head.py --report
"""
from __future__ import annotations

import sys
from contextlib import ExitStack
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from study_runs import study_main  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "mask_on_head.json"
SEEDS = range(20)
VARIANTS = ("before", "front", "shipped")
FRONT_SHARE = 0.2
WITHIN_DEGREES = 5.0


def _front_starts(search, points: np.ndarray, share: float):
    """``search.hypothesis_starts`` with every rotation placed twice: as shipped, and with the model's
    visible side on the mean of the ``share`` of ``points`` (the scan in the search's unit frame,
    centroid at the origin) nearest the scanner."""
    from statfit.registration.pose import hypotheses

    shipped = search.hypothesis_starts

    def starts(model_unit, model_normals, facing):
        poses = shipped(model_unit, model_normals, facing)
        depth = points @ facing
        front = points[depth >= np.quantile(depth, 1 - share)].mean(axis=0)
        return hypotheses.Poses(np.ones(2 * len(poses.scale)), np.concatenate([poses.rotation, poses.rotation]),
                                np.concatenate([poses.translation, front[None] + poses.translation]))

    return starts


def run_case(seed: int, variant: str) -> dict:
    """One person's scan, posed at random, and the face cut's pose searched under ``variant``."""
    from unittest import mock

    import torch
    from scipy.spatial.transform import Rotation

    from statfit.errors import StatfitError
    from statfit.model.cut import region_part
    from statfit.model.importers.cache import open_model
    from statfit.registration.pose import search
    from statfit.registration.pose.hypotheses import angle_between
    from statfit.structures.scan import Scan
    from statfit.synth.sample import sample_target, scan_from_view

    torch.set_num_threads(1)
    head = open_model(None)
    mask = region_part(head, "face")
    rng = np.random.default_rng(seed)
    points = scan_from_view(sample_target(head, rng), head.faces, rng, 4300, 30.0)
    pose = np.random.default_rng(1000 + seed)
    rotation = Rotation.random(random_state=pose.integers(2**32)).as_matrix()
    radius = float(np.sqrt(((head.template - head.template.mean(0)) ** 2).sum(1).mean()))
    shift = pose.normal(0, 3 * radius, 3)
    scan = Scan.from_points(points @ rotation.T + shift)
    row = {"seed": seed, "variant": variant}
    plausible = search.check_plausible

    def refusal_kept(*args, **kwargs):     # the pose is searched to its end; a refusal is recorded
        try:
            return plausible(*args, **kwargs)
        except StatfitError as refusal:
            row["refused"] = str(refusal)[:160]

    with ExitStack() as patches:
        patches.enter_context(mock.patch.object(search, "check_plausible", refusal_kept))
        if variant != "shipped":    # the score before: the scan's side alone, for every model
            patches.enter_context(mock.patch.object(search, "of_part_of_a_subject", lambda *_: False))
        if variant == "front":      # the scan in the search's unit frame, as estimate_pose makes it
            centred = scan.points - scan.points.mean(axis=0)
            units = 10.0 ** np.round(np.log10(np.sqrt((centred ** 2).sum(1).mean()) / mask.frame.scale))
            starts = _front_starts(search, centred / (units * mask.frame.scale), FRONT_SHARE)
            patches.enter_context(mock.patch.object(search, "hypothesis_starts", starts))
        try:
            found = search.estimate_pose(mask, scan)
            offset = found.transform.apply(mask.template) - (mask.template @ rotation.T + shift)
            row.update(degrees=angle_between(found.transform.rotation, rotation), score=found.score,
                       offset=float(np.sqrt((offset ** 2).sum(1).mean())) / radius)
        except Exception as error:  # noqa: BLE001 - a refusal is this case's result
            row["error"] = f"{type(error).__name__}: {error}"[:160]
    return row


def runs() -> list[tuple]:
    return [(seed, variant) for seed in SEEDS for variant in VARIANTS]


def report(rows: list[dict]) -> str:
    lines = [f"| variant | scans | pose within {WITHIN_DEGREES:g}° | of those refused | wrong pose | of those refused | "
             "failed | median offset, right poses (head radii) |", "|---|---|---|---|---|---|---|---|"]
    for variant in VARIANTS:
        mine = [row for row in rows if row["variant"] == variant]
        posed = [row for row in mine if "error" not in row]
        right = [row for row in posed if row["degrees"] <= WITHIN_DEGREES]
        wrong = [row for row in posed if row["degrees"] > WITHIN_DEGREES]
        median = np.median([row["offset"] for row in right]) if right else float("nan")
        lines.append(f"| {variant} | {len(mine)} | {len(right)} | {sum('refused' in r for r in right)} | {len(wrong)} | "
                     f"{sum('refused' in r for r in wrong)} | {len(mine) - len(posed)} | {median:.3f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    study_main(__doc__, run_case, runs, RESULTS, report, key=lambda row: (row["seed"], row["variant"]))
