"""Which scans the pose search refuses: people of four model families under each family's model,
with and without clutter, against things that are no person (a plane, a sphere, a box, ...).

`--align auto` refuses a scan whose best fit needs coefficients far beyond the model's people
(statfit/registration/pose/scoring.py, ``check_plausible``) unless that fit explains most of the
scan's points. Clutter (hair, neck and shoulders) explains nothing, so on a cluttered scan of a person
outside the model's people that share stays low and the person was refused. Each case runs
``estimate_pose`` (one thread) with the check wrapped, so the search runs to its end and the row keeps
what the check saw: the coefficients' RMS and largest, the explained share, the share of the fit's
facing surface that the scan supports (``supported_share``), the decision (ok / warn / refuse) and,
for people, the pose's angle from the truth; for a model's own people whose scan is not refused, the
register default's mean vertex error. "before" is the rule before docs/studies.md §40, derived from
the same row's facts.

- people: realistic scans (benchmarks/families.py; one view, yaw within ±40°, any rotation and
  offset, mm, 4,300 points on the person, clutter 0, 0.5 and 2 per person point), seeds 0–9;
- shapes: a plane, a sphere, a tube, a box, a cylinder, a torus, a capsule, a half sphere and a bumpy
  ball, each in a random rotation, the model's size (0.6–1.5× from seed 3 on), in mm, seeds 0–8;
- sparse and dense scans: the three real families' people under their models, seeds 6–7, at 1,000
  and 20,000 points (the supported share's tolerance widens with a sparse scan's spacing).

Which seeds chose which limit and which checked them: ``GROUPS``, ``SHAPE_GROUPS``.

    python studies/pose_refusals.py [--report]

~35 min on 2 cores; rows in studies/results/pose_refusals.json (docs/studies.md §40).
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "studies"))

from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "pose_refusals.json"
FAMILIES = ("ict", "ict-mask", "makehuman", "embedded")
SHAPES = ("plane", "sphere", "tube", "box", "cylinder", "torus", "capsule", "halfsphere", "bumpy")
CLUTTER = (0.0, 0.5, 2.0)
PEOPLE_SEEDS, SHAPE_SEEDS = 10, 9
POINTS, OTHER_POINTS, OTHER_POINTS_SEEDS = 4300, (1000, 20000), range(6, 8)
REAL = ("ict", "ict-mask", "makehuman")
# which seeds chose the rule's limits (docs/studies.md §40): people 0–1 the band's FAR_RMS, FAR_COEFFICIENT and
# SUPPORTED; 2–5 showed wrong poses in it, which its clarity condition (the search's own AMBIGUITY) left out;
# shapes 0–5 BEYOND_ANY_PERSON and NOTHING_EXPLAINED; people 6–9 and shapes 6–8 checked them all
GROUPS = (("seeds 0–1 (chose the band)", range(0, 2)), ("seeds 2–5 (chose its clarity)", range(2, 6)),
          ("seeds 6–9 (checked it)", range(6, 10)))
SHAPE_GROUPS = (("0–2", range(0, 3)), ("3–5, sized 0.6–1.5×", range(3, 6)), ("6–8, sized 0.6–1.5×: checked", range(6, 9)))
RIGHT_DEGREES = 15.0        # a pose this near the truth is the person's (another family's heads tilt by ≤ 13°)


def shape_scan(model_name: str, kind: str, seed: int):
    """A scan of ``kind`` at ``model_name``'s size (times 0.6–1.5 from seed 3 on), in a random
    rotation, in mm."""
    import numpy as np
    import trimesh
    from families import METRES_PER_UNIT, family_model

    from statfit.structures.scan import Scan
    from statfit.synth.scanner import neck_tube

    template = family_model(model_name).template
    rng = np.random.default_rng(seed)
    r = float(np.ptp(template, axis=0).max() / 2) * (rng.uniform(0.6, 1.5) if seed >= 3 else 1.0)
    if kind == "plane":
        mesh = trimesh.creation.box([2 * r, 2 * r, 1e-3 * r])
    elif kind == "sphere":
        mesh = trimesh.creation.icosphere(4, radius=r)
    elif kind == "tube":
        mesh = neck_tube(template)
    elif kind == "box":
        mesh = trimesh.creation.box([1.4 * r, 1.8 * r, 1.2 * r])
    elif kind == "cylinder":
        mesh = trimesh.creation.cylinder(radius=0.7 * r, height=2 * r, sections=64)
    elif kind == "torus":
        mesh = trimesh.creation.torus(0.8 * r, 0.3 * r)
    elif kind == "capsule":
        mesh = trimesh.creation.capsule(height=r, radius=0.6 * r, count=[32, 32])
    elif kind == "halfsphere":
        ball = trimesh.creation.icosphere(4, radius=r)
        mesh = trimesh.Trimesh(ball.vertices, ball.faces[ball.triangles_center[:, 2] > 0])
    else:
        ball = trimesh.creation.icosphere(5, radius=r)
        bumps = 1 + 0.15 * np.sin(5 * ball.vertices[:, :1] / r) * np.cos(4 * ball.vertices[:, 1:2] / r)
        mesh = trimesh.Trimesh(ball.vertices * bumps, ball.faces)
    if kind != "sphere":
        mesh = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, r / 20))
    mesh.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
    mesh.apply_scale(1000.0 * METRES_PER_UNIT[model_name])
    return Scan.from_mesh(mesh.vertices, mesh.faces)


def recording(checked, into: dict):
    """``check_plausible`` (``checked``) that keeps the facts it saw and its decision (ok / warn /
    refuse) in ``into`` instead of raising, so the pose search runs to its end. The first search's
    refusal is raised all the same: it is what sends the search to its second grid (step 7,
    docs/studies.md §44), whose choice is the last word kept."""
    import numpy as np

    from statfit.errors import StatfitError

    def recorded(matched, explained, coefficients, tolerance, has_landmarks=True, **facts):
        first = "decision" not in into
        into.update(matched=matched, explained=explained, rms=float(np.sqrt(np.mean(coefficients**2))),
                    largest=float(np.abs(coefficients).max()), **facts)
        try:
            into["decision"] = "warn" if checked(matched, explained, coefficients, tolerance, has_landmarks,
                                                 **facts) else "ok"
        except StatfitError:
            into["decision"] = "refuse"
            if first:
                raise

    return recorded


def run_case(model_name: str, subject: str, seed: int, clutter: float, points: int = POINTS) -> dict:
    import warnings

    import numpy as np
    import torch
    from families import family_model, person

    import statfit.registration.pose.search as search
    from statfit.errors import StatfitError
    from statfit.structures.scan import Scan
    from statfit.synth.scanner import realistic_scan

    torch.set_num_threads(1)
    row = {"model": model_name, "subject": subject, "seed": seed, "clutter": clutter, "points": points}
    made = None
    if subject in FAMILIES:
        rng = np.random.default_rng(seed)
        made = realistic_scan(person(subject, seed), family_model(subject).faces, rng, points,
                              yaw_deg=rng.uniform(-40, 40), clutter=clutter, units="mm", posed=True)
        scan = Scan.from_mesh(made.vertices, made.faces)
    else:
        scan = shape_scan(model_name, subject, seed)
    checked = search.check_plausible
    search.check_plausible = recording(checked, row)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            found = search.estimate_pose(family_model(model_name), scan, threads=1)
    except StatfitError as error:           # refused before the check (nothing matched): no pose
        return {**row, "decision": "refuse", "error": str(error)[:120]}
    finally:
        search.check_plausible = checked
    row.update(score=found.score, runner_up=found.runner_up)
    if made is not None:
        turn = found.transform.rotation.T @ made.transform.rotation
        row["degrees"] = float(np.degrees(np.arccos(np.clip((np.trace(turn) - 1) / 2, -1, 1))))
    if subject == model_name and row["decision"] != "refuse":     # the model's topology: errors per vertex
        from statfit.registration.job import register

        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                fitted = register(family_model(model_name), scan, threads=1).vertices
        except StatfitError as refusal:     # register fits the jobs' model (§44's rule), whose search may refuse
            row["register_refused"] = str(refusal)[:120]
            return row
        row["vertex_mm"] = float(np.linalg.norm(fitted - made.truth, axis=1).mean())
    return row


def runs() -> list[tuple]:
    people = [(model, subject, seed, clutter, POINTS) for model in FAMILIES for subject in FAMILIES
              for seed in range(PEOPLE_SEEDS) for clutter in CLUTTER]
    shapes = [(model, kind, seed, 0.0, POINTS) for model in FAMILIES for kind in SHAPES for seed in range(SHAPE_SEEDS)]
    sparse_and_dense = [(model, subject, seed, clutter, points) for model in REAL for subject in REAL
                        for seed in OTHER_POINTS_SEEDS for clutter in CLUTTER for points in OTHER_POINTS]
    return people + shapes + sparse_and_dense


def before(row: dict) -> str:
    """The decision without the supported band (the rule before docs/studies.md §40)."""
    from statfit.registration.pose.scoring import EXPLAINED, IMPLAUSIBLE_COEFFICIENT, IMPLAUSIBLE_RMS

    if "error" in row:
        return "refuse"
    if row["rms"] <= IMPLAUSIBLE_RMS and row["largest"] <= IMPLAUSIBLE_COEFFICIENT:
        return "ok"
    return "warn" if row["explained"] >= EXPLAINED else "refuse"


def report(rows: list[dict]) -> str:
    people = [r for r in rows if r["subject"] in FAMILIES and r.get("points", POINTS) == POINTS]
    shapes = [r for r in rows if r["subject"] not in FAMILIES]
    right = lambda r: r.get("degrees", 180.0) < RIGHT_DEGREES      # noqa: E731
    lines = []
    for title, seeds in GROUPS:
        mine = [r for r in people if r["seed"] in seeds]
        lines += ["", f"People, {title}: scans refused before → now (of them with the pose right, within "
                  f"{RIGHT_DEGREES:.0f}°), and wrong poses accepted before → now", "",
                  "| model | people | scans | refused | refused, pose right | wrong pose accepted |",
                  "|---|---|---|---|---|---|"]
        for model in FAMILIES:
            for subject in FAMILIES:
                pair = [r for r in mine if (r["model"], r["subject"]) == (model, subject)]
                if pair:
                    lines.append(_people_row(f"{model} | {subject}", pair, right))
        lines.append(_people_row("all | ", mine, right))
    lines += ["", "The register default on its own model's people (every seed; mean vertex error, mm): the scans "
              "accepted before, and those accepted only now", "",
              "| model | clutter | accepted before: scans | mm | accepted now only: scans | mm |", "|---|---|---|---|---|---|"]
    for model in FAMILIES:
        for clutter in CLUTTER:
            mine = [r for r in people if (r["model"], r["subject"], r["clutter"]) == (model, model, clutter)
                    and "vertex_mm" in r]
            old, new = ([r["vertex_mm"] for r in mine if (before(r) != "refuse") == was] for was in (True, False))
            lines.append(f"| {model} | {clutter} | {len(old)} | {_mean(old)} | {len(new)} | {_mean(new)} |")
    lines += ["", "Shapes: accepted before → now, by rotation seeds", "",
              "| model | shapes | " + " | ".join(f"accepted ({title})" for title, _ in SHAPE_GROUPS)
              + " | least RMS | its largest, supported |", "|---|---|---|---|---|---|---|"]
    for model in FAMILIES:
        mine = [r for r in shapes if r["model"] == model]
        if not mine:
            continue
        accepted = [f"{sum(before(r) != 'refuse' for r in part)} → {sum(r['decision'] != 'refuse' for r in part)}"
                    for part in ([r for r in mine if r["seed"] in seeds] for _, seeds in SHAPE_GROUPS)]
        nearest = min((r for r in mine if "rms" in r), key=lambda r: r["rms"])
        lines.append(f"| {model} | {len(mine)} | {' | '.join(accepted)} | {nearest['rms']:.2f} "
                     f"({nearest['subject']}) | {nearest['largest']:.1f}, {nearest['supported']:.2f} |")
    lines += ["", f"Sparse and dense scans: the real families' people under their models, seeds "
              f"{OTHER_POINTS_SEEDS.start}–{OTHER_POINTS_SEEDS.stop - 1}, every clutter", "",
              "| points | scans | refused | refused, pose right | wrong pose accepted | supported, right poses: least / median |",
              "|---|---|---|---|---|---|"]
    for points in sorted({POINTS, *OTHER_POINTS}):
        mine = [r for r in rows if r.get("points", POINTS) == points and r["subject"] in REAL and r["model"] in REAL
                and r["seed"] in OTHER_POINTS_SEEDS]
        held = sorted(r["supported"] for r in mine if right(r) and "supported" in r)
        lines.append(_people_row(str(points), mine, right)[:-1]
                     + (f"| {held[0]:.2f} / {held[len(held) // 2]:.2f} |" if held else "| – |"))
    accepted = [r for r in shapes if r["decision"] != "refuse"]
    lines += ["", "Shapes accepted now: " + (", ".join(
        f"{r['subject']} {r['seed']} under {r['model']} (RMS {r['rms']:.2f}, largest {r['largest']:.1f}, "
        f"explained {r['explained']:.2f}, supported {r['supported']:.2f})" for r in accepted) or "none")]
    return "\n".join(lines)


def _mean(values: list[float]) -> str:
    return f"{sum(values) / len(values):.2f}" if values else "–"


def _people_row(label: str, rows: list[dict], right) -> str:
    refused_before = [r for r in rows if before(r) == "refuse"]
    refused_now = [r for r in rows if r["decision"] == "refuse"]
    wrong_before = sum(before(r) != "refuse" and not right(r) for r in rows)
    wrong_now = sum(r["decision"] != "refuse" and not right(r) for r in rows)
    return (f"| {label} | {len(rows)} | {len(refused_before)} → {len(refused_now)} | "
            f"{sum(map(right, refused_before))} → {sum(map(right, refused_now))} | {wrong_before} → {wrong_now} |")


if __name__ == "__main__":
    study_main(__doc__, run_case, runs, RESULTS, report,
               key=lambda r: (r["model"], r["subject"], r["seed"], r["clutter"], r.get("points", POINTS)))
