"""Why `render` without the modes' rigid motion loses on ICT's own cases (docs/studies.md §45), and
whether taking out the modes' rotations alone, or all their rigid motion but a translation along
the viewing axis, keeps the gain without the loss.

The render alignment finds a rotation and a move parallel to the image but holds the depth (the
translation along the viewing axis trades with the shape's size from one view). As built, the
modes' translations can still move the fit in depth, under their prior; without the rigid motion
nothing can. So: the modes less their small rotations about the template's centroid only (their
translations kept), and the modes without their rigid motion plus one mode, a translation along the
map's viewing axis (its standard deviation that of the modes' translations along it), and the
modes without rigid motion with the alignment's translation free along the viewing axis too
(session 42: it runs away in depth), beside as built and without all rigid motion, on

1. §5's four ICT cases at 512² (studies/study_render.py; mean vertex error and its mean offset
   along the viewing axis, % of the RMS radius; the default), and
2. §45's misplaced cross-family cases with ICT's head (studies/cross_family_render.py, 256²,
   people misplaced by 5° and 5%; the default).

    python studies/rigid_free_depth.py            # ~25 min on 2 cores
    python studies/rigid_free_depth.py --report
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from rigid_free_modes import FREED  # noqa: E402
from rigid_free_render import MISPLACED, PEOPLE, SEEDS, SIZE  # noqa: E402
from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "rigid_free_depth.json"
ROTATION_FREE = " without rigid rotation"
DEPTH_KEPT = " without rigid motion but depth"
DEPTH_FOUND = " without rigid motion, depth aligned"
VARIANTS = ("ict", "ict" + FREED, "ict" + ROTATION_FREE, "ict" + DEPTH_KEPT, "ict" + DEPTH_FOUND)
VIEW_AXIS: list[np.ndarray] = []   # the case's viewing axis (model frame), for DEPTH_KEPT's model


def without_rotation(model):
    """``model`` with its modes' small rotations about the template's centroid taken out (the part
    of each mode's least-squares rigid motion not a translation), its translations kept."""
    from statfit.model.cut import rigid_motion_basis
    from statfit.model.statmodel import model_from_arrays

    turns = rigid_motion_basis(model.template)[:, 3:]      # the rotations, orthogonal to the translations
    modes = model.basis * model.std
    shaped = modes - turns @ (turns.T @ modes)
    return model_from_arrays(model.template, model.faces, shaped.reshape(model.num_vertices, 3, -1), model.landmarks,
                             model.regions, source=f"{model.source}{ROTATION_FREE}")


def with_depth(model, freed, axis: np.ndarray):
    """``freed`` (``model`` without its modes' rigid motion) with one mode more: a translation along
    ``axis`` (3,), unit, whose standard deviation is that of ``model``'s modes' translations along it."""
    from statfit.model.statmodel import model_from_arrays

    n = model.num_vertices
    modes = (model.basis * model.std).reshape(n, 3, -1)
    depth = float(np.sqrt(((np.einsum("nik,i->k", modes, axis) / n) ** 2).sum()))
    shaped = np.concatenate([(freed.basis * freed.std).reshape(n, 3, -1),
                             np.broadcast_to(axis * depth, (n, 3))[:, :, None]], axis=2)
    return model_from_arrays(freed.template, freed.faces, shaped, freed.landmarks, freed.regions,
                             source=f"{model.source}{DEPTH_KEPT}")


def variant_model(plain, name: str):
    """``plain(family)`` (a family's model), or it without rotation, without all rigid motion, or
    without it but a translation along VIEW_AXIS, by ``name``'s suffix."""
    from statfit.model.cut import without_rigid_motion

    if name.endswith(DEPTH_KEPT):
        model = plain(name.removesuffix(DEPTH_KEPT))
        return with_depth(model, without_rigid_motion(model), VIEW_AXIS[-1])
    if name.endswith(DEPTH_FOUND):
        return without_rigid_motion(plain(name.removesuffix(DEPTH_FOUND)))
    if name.endswith(ROTATION_FREE):
        return without_rotation(plain(name.removesuffix(ROTATION_FREE)))
    if name.endswith(FREED):
        return without_rigid_motion(plain(name.removesuffix(FREED)))
    return plain(name)


def use_variants() -> None:
    """``families.family_model`` answers the VARIANTS' names (in this process); the jobs' rule off,
    so each variant is fitted as made."""
    import families
    import statfit.model.cut

    statfit.model.cut.MOSTLY_RIGID = 1.0
    if getattr(families, "_rotation_variants", False):
        return
    plain = families.family_model
    families.family_model = lambda name: variant_model(plain, name)
    for name in VARIANTS:
        families.METRES_PER_UNIT.setdefault(name, families.METRES_PER_UNIT["ict"])
    families._rotation_variants = True


def align_depth(free: bool) -> None:
    """Let the render alignment move the pose along the viewing axis too (``free``), or not (as built)."""
    import statfit.render.job as job
    from statfit.core.pose import fit_pose

    job.fit_pose = (lambda *args, **kwargs: fit_pose(*args, **(kwargs | {"fixed_axis": None}))) if free else fit_pose


def fit_case(kind: str, variant: str, case: str, seed: int) -> dict:
    import torch

    torch.set_num_threads(1)
    use_variants()
    align_depth(variant.endswith(DEPTH_FOUND))
    row = {"kind": kind, "variant": variant, "case": case, "seed": seed}
    if kind == "cross-family":
        from cross_family_render import fit_case as fit_view, render_case

        VIEW_AXIS.append(render_case(case, "ict", seed, SIZE, MISPLACED)[2].rotation[2].numpy())
        return fit_view(case, variant, seed, "default", SIZE, MISPLACED) | row
    from common import ICT
    from families import family_model
    from statfit.render.job import reconstruct
    from study_render import CASES, make_target

    target = next(c for c in CASES if c.name == case)     # the person: a sample of the model as built
    gt, camera, normal_map = make_target(family_model("ict"), ICT / "ict_face_expressions.npz", target, 512)
    VIEW_AXIS.append(camera.rotation[2].numpy())
    fit = reconstruct(family_model(variant), normal_map, camera, "default", threads=1).vertices
    radius = float(np.sqrt(((gt - gt.mean(axis=0)) ** 2).sum(axis=1).mean()))
    depth = float((fit - gt).mean(axis=0) @ camera.rotation[2].numpy()) / radius
    return row | {"all": float(np.linalg.norm(fit - gt, axis=1).mean()) / radius, "depth_offset": depth}


def runs() -> list[tuple]:
    from families import build_all
    from study_render import CASES

    build_all(list(PEOPLE), len(SEEDS))
    return ([("in-family", v, c.name, 0) for c in CASES for v in VARIANTS]
            + [("cross-family", v, p, s) for p in PEOPLE for s in SEEDS for v in VARIANTS])


def report(rows: list[dict]) -> str:
    lines = ["| kind | case | " + " | ".join(v.removeprefix("ict").strip() or "as built" for v in VARIANTS) + " |",
             "|---|---|" + "---|" * len(VARIANTS)]
    by = {(r["kind"], r["case"], r["seed"], r["variant"]): r for r in rows}
    for kind, case, seed in dict.fromkeys((r["kind"], r["case"], r["seed"]) for r in rows):
        cells = []
        for v in VARIANTS:
            r = by.get((kind, case, seed, v), {})
            value = 100 * r["all"] if kind == "in-family" and "all" in r else r.get("all", np.nan)
            depth = f" (depth {100 * r['depth_offset']:+.2f})" if "depth_offset" in r else ""
            cells.append(f"{value:.2f}{depth}")
        lines.append(f"| {kind} | {case} {seed if kind == 'cross-family' else ''} | " + " | ".join(cells) + " |")
    for kind in ("in-family", "cross-family"):
        mean = [np.nanmean([(100 if kind == "in-family" else 1) * by[k]["all"] for k in by if k[0] == kind and k[3] == v
                            and "all" in by[k]]) for v in VARIANTS]
        lines.append(f"| {kind} | mean | " + " | ".join(f"{m:.2f}" for m in mean) + " |")
    return "Error, % of the RMS radius (in family: per vertex; cross-family: surface to fit).\n\n" + "\n".join(lines)


if __name__ == "__main__":
    study_main(__doc__, fit_case, runs, RESULTS, report,
               key=lambda row: (row["kind"], row["variant"], row["case"], row["seed"]))
