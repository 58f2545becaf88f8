"""A model's modes without rigid motion (``statfit.model.cut.without_rigid_motion``): does a model
whose modes mostly move it (MakeHuman's head, cut from a body model: 99.8% of its modes' variance is
rigid motion) guess the unseen half of a face better without it, and a model cut the same way whose
modes mostly do not (ICT's face mask, 30%)? (docs/studies.md §43.)

§19's protocol (studies/cross_family_landmarks.py: one realistic view, split into halves, each half
fitted with its own inner landmarks, the other half held out; mm), with each of the two models as
built and without its modes' rigid motion, side by side, on the people of the three landmarked
families (ICT's, the mask's, MakeHuman's), 2 people each, 4 halves; the default, `statistical`,
`laplacian` and the landmark-placed mean. The rigid share of each family's modes is printed first.

    python studies/rigid_free_modes.py            # ~12 min on 2 cores
    python studies/rigid_free_modes.py --report
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "rigid_free_modes.json"
PEOPLE = ("ict", "ict-mask", "makehuman")
FREED = " without rigid motion"
MODELS = ("makehuman", "ict-mask")     # MakeHuman's head: chosen on; the face mask: checked on
VARIANTS = tuple(name + suffix for name in MODELS for suffix in ("", FREED))
METHODS = ("mean", "default", "statistical", "laplacian")
SEEDS = (0, 1)


def use_variants() -> None:
    """``families.family_model``, ``landmarked_model`` and ``METRES_PER_UNIT`` answer a family's
    name with :data:`FREED` too (in this process): the model without rigid motion; and a model as
    built is fitted as built (the jobs' ``rigid_modes="auto"`` never drops its rigid motion)."""
    import families
    from statfit.model.cut import without_rigid_motion

    if getattr(families, "_variants_added", False):
        return
    import statfit.model.cut

    statfit.model.cut.MOSTLY_RIGID = 1.0   # "as built" stays as built: the jobs' automatic rule (§44) off
    plain_model, plain_landmarked = families.family_model, families.landmarked_model

    def family_model(name: str):
        if name.endswith(FREED):
            return without_rigid_motion(plain_model(name.removesuffix(FREED)))
        return plain_model(name)

    def landmarked_model(name: str):
        if name.endswith(FREED):
            return without_rigid_motion(plain_landmarked(name.removesuffix(FREED)))
        return plain_landmarked(name)

    families.family_model, families.landmarked_model, families._variants_added = family_model, landmarked_model, True
    for name in list(families.METRES_PER_UNIT):
        families.METRES_PER_UNIT[name + FREED] = families.METRES_PER_UNIT[name]


def fit_case(people: str, variant: str, seed: int, half: str, method: str) -> dict:
    use_variants()
    from cross_family_landmarks import fit_case as fit_half

    return fit_half(people, variant, seed, half, method)


def rigid_shares() -> str:
    """Each family's share of its modes' variance that is rigid motion, as built."""
    from families import CHECK_FAMILIES, FAMILIES, family_model
    from statfit.model.cut import without_rigid_motion

    lines = ["| family | rigid share of the modes' variance | largest std without it ÷ as built |", "|---|---|---|"]
    for name in FAMILIES + CHECK_FAMILIES:
        model = family_model(name)
        free = without_rigid_motion(model)
        share = 1.0 - float((free.std**2).sum() / (model.std**2).sum())
        lines.append(f"| {name} | {share:.3f} | {free.std[0] / model.std[0]:.3f} |")
    return "\n".join(lines)


def runs() -> list[tuple]:
    from families import build_all

    build_all(list(PEOPLE), len(SEEDS))
    return [(p, v, s, h, m) for p in PEOPLE for v in VARIANTS for s in SEEDS
            for h in ("left", "right", "upper", "lower") for m in METHODS]


def report(rows: list[dict]) -> str:
    from cross_family_landmarks import report as half_report

    return rigid_shares() + "\n\n" + half_report(rows)


if __name__ == "__main__":
    study_main(__doc__, fit_case, runs, RESULTS, report,
               key=lambda row: (row["people"], row["model"], row["seed"], row["half"], row["method"]))
