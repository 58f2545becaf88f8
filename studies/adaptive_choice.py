"""Choosing the method per scan from the scan itself (issue 37, part 3; docs/studies.md §20).

On §19's cases (studies/cross_family_landmarks.py: a half face of a person from one model family,
fitted with another family's model and that half's landmarks, scored on the other half), the
default and ``laplacian`` each win on some pairs. Can a fit tell, from the points it was given,
which one will guess the unseen part better? The rule tried here, which needs nothing but the scan
and its landmarks:

- place the model's mean by the landmarks and take the direction d from the scan's centroid towards
  the mean's (towards where the scan does not reach);
- hold out the quarter of the scan's points farthest along d (the scan's edge facing the unseen
  part) and fit each candidate method to the rest, with the landmarks;
- keep the candidate whose fit lies nearest the held-out quarter (mean distance to its surface).

The chosen method's error on the real test (the other half) is then §19's row of that method fitted
to the whole half (stored in studies/results/cross_family_landmarks.json): this study runs only the
validation fits. Reported per (people, model) pair: the mean held-out error of the default,
``laplacian``, the choice, the better of the two per case (the oracle), and how often the choice
agrees with the oracle.

    python studies/adaptive_choice.py --people 2      # ~5 min on 2 cores, after cross_family_landmarks.py
    python studies/adaptive_choice.py --in-family     # §15's ICT cases, after held_out_half.py (~2 min)
    python studies/adaptive_choice.py --whole-faces   # §12's ICT whole faces, after landmark_term.py (~1 min)
    python studies/adaptive_choice.py --report
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from cross_family import inside_distance  # noqa: E402
from cross_family_landmarks import HALVES, RESULTS as FULL_FITS, case_data  # noqa: E402
from families import LANDMARKED  # noqa: E402
from study_runs import run_or_report  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "adaptive_choice.json"
IN_FAMILY = ROOT / "studies" / "results" / "adaptive_choice_in_family.json"
IN_FAMILY_K = 50   # §15's model: ICT's first 50 modes
WHOLE_FACES = ROOT / "studies" / "results" / "adaptive_choice_whole_faces.json"
WHOLE_FACE_WEIGHT = 10.0   # §12's landmark weight
CANDIDATES = ("default", "laplacian")
HELD_SHARE = 0.25


def validation_split(points: np.ndarray, template_placed: np.ndarray) -> np.ndarray:
    """(M,) bool: the HELD_SHARE of ``points`` (M, 3) farthest along the direction from their
    centroid towards the placed template's (N, 3) centroid."""
    direction = template_placed.mean(axis=0) - points.mean(axis=0)
    direction /= max(np.linalg.norm(direction), 1e-12)
    along = points @ direction
    return along >= np.quantile(along, 1.0 - HELD_SHARE)


def single_threaded() -> None:
    """One torch thread, subnormals flushed: as every study fit runs (set before the case is built)."""
    import torch

    from statfit.core.threads import flush_denormals_everywhere

    torch.set_num_threads(1)
    flush_denormals_everywhere()


def validation_fit(model, points: np.ndarray, landmarks: np.ndarray, method: str, normals: np.ndarray | None = None,
                   **options) -> dict:
    """``method`` fitted to ``points`` (M, 3; ``normals`` (M, 3) or None) less their validation
    quarter (:func:`validation_split`, from the mean placed by ``landmarks``): the quarter's mean
    distance to the fit (the points' units) and the fit's seconds."""
    from default_candidates import register_candidate
    from statfit.registration.prealign import landmark_alignment
    from statfit.structures.scan import Scan

    held = validation_split(points, landmark_alignment(model, landmarks).apply(model.template))
    kept = points[~held] if normals is None else Scan(points[~held], normals[~held])
    result = register_candidate(method, model, kept, landmarks=landmarks, threads=1, **options)
    return {"validation": float(np.nanmean(inside_distance(points[held], result.vertices, model.faces))),
            "seconds": result.seconds}


def chosen_method(checks: dict, case: tuple) -> str:
    """The candidate whose validation distance ``checks[(*case, method)]`` is the lowest."""
    return min(CANDIDATES, key=lambda method: checks[(*case, method)])


def fit_case(people: str, model_family: str, seed: int, half: str, method: str) -> dict:
    single_threaded()
    from families import landmarked_model

    data = case_data(people, seed, half)
    row = {"people": people, "model": model_family, "seed": seed, "half": half, "method": method}
    try:
        return row | validation_fit(landmarked_model(model_family), data["seen"].points, data["landmarks"], method,
                                    data["seen"].normals)
    except Exception as exc:   # a refusal is a result too
        return row | {"error": f"{type(exc).__name__}: {exc}".splitlines()[0]}


def fit_in_family(name: str, half: str, method: str) -> dict:
    """The validation fit of ``method`` on §15's case (studies/held_out_half.py): an ICT person
    outside ICT's first 50 modes, a half face with its landmarks (validation in mm; ICT is in cm)."""
    single_threaded()
    from cases import ict_model
    from held_out_half import case_data as in_family_case
    from statfit.model.statmodel import with_landmarks

    data = in_family_case(name, half)
    model = with_landmarks(ict_model(), data["indices"]).truncated(IN_FAMILY_K)
    fitted = validation_fit(model, data["seen"], data["landmarks"], method)
    return {"case": name, "half": half, "method": method, "seconds": fitted["seconds"],
            "validation": 10.0 * fitted["validation"]}


def in_family_report(rows: list[dict]) -> str:
    """§15's cases: the held-out half (mm, studies/results/held_out_half.json) of each candidate and
    of the choice."""
    from held_out_half import RESULTS as HALF_FITS

    full = {(r["case"], r["half"], r["method"]): r["held"] for r in json.loads(HALF_FITS.read_text())
            if "case" in r and r.get("k") == IN_FAMILY_K}
    checks = {(r["case"], r["half"], r["method"]): r["validation"] for r in rows}
    cases = sorted({k[:2] for k in checks if all((*k[:2], c) in checks and (*k[:2], c) in full for c in CANDIDATES)})
    chosen = [full[(*c, chosen_method(checks, c))] for c in cases]
    laplacian_chosen = sum(chosen_method(checks, c) == "laplacian" for c in cases)
    values = {m: float(np.mean([full[(*c, m)] for c in cases])) for m in (*CANDIDATES, "mean")}
    return "\n".join([
        "In family (§15: ICT people outside ICT's first 50 modes, half faces with landmarks): held-out half (mm).", "",
        "| cases | default | laplacian | chosen | chosen ÷ default | chosen ÷ mean | laplacian chosen |",
        "|---|---|---|---|---|---|---|",
        f"| {len(cases)} | {values['default']:.3f} | {values['laplacian']:.3f} | {np.mean(chosen):.3f} | "
        f"{np.mean(chosen) / values['default']:.3f} | {np.mean(chosen) / values['mean']:.2f} | "
        f"{laplacian_chosen}/{len(cases)} |"])


def fit_whole_face(case: str, method: str) -> dict:
    """The validation fit of ``method`` on §12's case (studies/landmark_term.py): a whole ICT face
    scan in millimetres with its landmarks, the nose tip's misplaced."""
    single_threaded()
    from landmark_term import case_data as whole_face_case

    data = whole_face_case(case)
    return {"case": case, "method": method} | validation_fit(data["model"], data["points"], data["landmarks"], method,
                                                              landmark_weight=WHOLE_FACE_WEIGHT)


def whole_face_report(rows: list[dict]) -> str:
    """§12's cases: the all-vertex error (mm, studies/results/landmark_term_2026-11-26.json) of each
    candidate fitted to the whole scan, and of the choice."""
    stored = json.loads((ROOT / "studies" / "results" / "landmark_term_2026-11-26.json").read_text())
    full = {(r["case"], r["method"]): r["all_mm"] for r in stored if r["weight"] == WHOLE_FACE_WEIGHT}
    checks = {(r["case"], r["method"]): r["validation"] for r in rows}
    cases = sorted({c for c, _ in checks if all((c, m) in checks and (c, m) in full for m in CANDIDATES)})
    picks = {c: chosen_method(checks, (c,)) for c in cases}
    values = {m: float(np.mean([full[(c, m)] for c in cases])) for m in CANDIDATES}
    chosen = float(np.mean([full[(c, picks[c])] for c in cases]))
    return "\n".join([
        "Whole faces (§12: ICT people, landmarks with the nose tip 20 mm off): all-vertex error (mm).", "",
        "| cases | default | laplacian | chosen | chosen ÷ default | laplacian chosen |", "|---|---|---|---|---|---|",
        f"| {len(cases)} | {values['default']:.3f} | {values['laplacian']:.3f} | {chosen:.3f} | "
        f"{chosen / values['default']:.3f} | {sum(p == 'laplacian' for p in picks.values())}/{len(cases)} |"])


def report(rows: list[dict]) -> str:
    full = {(r["people"], r["model"], r["seed"], r["half"], r["method"]): r
            for r in json.loads(FULL_FITS.read_text()) if "held" in r}
    checks = {(r["people"], r["model"], r["seed"], r["half"], r["method"]): r["validation"]
              for r in rows if "validation" in r}
    pairs = sorted({(r["people"], r["model"]) for r in rows})
    lines = ["Held-out half (mm, §19's fits of the whole half) of each candidate, of the candidate the "
             "validation quarter chose, and of the better candidate per case (oracle); how often the "
             "choice is the oracle's; the choice ÷ the default, ÷ the landmark-placed mean.", "",
             "| people | model | cases | default | laplacian | chosen | oracle | agrees | chosen ÷ default | "
             "chosen ÷ mean | laplacian chosen |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    totals = {name: [] for name in ("default", "laplacian", "chosen", "oracle", "mean")}
    for people, model in pairs:
        cases = sorted({(s, h) for (p, m, s, h, _) in checks if (p, m) == (people, model)})
        cases = [c for c in cases if all((people, model, *c, k) in checks and (people, model, *c, k) in full
                                         for k in CANDIDATES) and (people, model, *c, "mean") in full]
        if not cases:
            continue
        values = {name: [] for name in totals}
        picked_laplacian = agree = 0
        for case in cases:
            held = {k: full[(people, model, *case, k)]["held"] for k in CANDIDATES}
            chosen = chosen_method(checks, (people, model, *case))
            oracle = min(CANDIDATES, key=held.get)
            picked_laplacian += chosen == "laplacian"
            agree += chosen == oracle
            for name, value in (("default", held["default"]), ("laplacian", held["laplacian"]),
                                ("chosen", held[chosen]), ("oracle", held[oracle]),
                                ("mean", full[(people, model, *case, "mean")]["held"])):
                values[name].append(value)
        means = {name: float(np.mean(v)) for name, v in values.items()}
        for name, v in values.items():
            totals[name] += v
        lines.append(f"| {people} | {model} | {len(cases)} | {means['default']:.2f} | {means['laplacian']:.2f} | "
                     f"{means['chosen']:.2f} | {means['oracle']:.2f} | {agree}/{len(cases)} | "
                     f"{means['chosen'] / means['default']:.2f} | {means['chosen'] / means['mean']:.2f} | "
                     f"{picked_laplacian}/{len(cases)} |")
    if totals["chosen"]:
        t = {name: float(np.mean(v)) for name, v in totals.items()}
        lines.append(f"| all | all | {len(totals['chosen'])} | {t['default']:.2f} | {t['laplacian']:.2f} | "
                     f"{t['chosen']:.2f} | {t['oracle']:.2f} | | {t['chosen'] / t['default']:.2f} | "
                     f"{t['chosen'] / t['mean']:.2f} | |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--people", type=int, default=2, help="people per family")
    parser.add_argument("--families", nargs="*", default=list(LANDMARKED), help=f"of {', '.join(LANDMARKED)}")
    parser.add_argument("--in-family", action="store_true", help="§15's ICT cases instead of §19's")
    parser.add_argument("--whole-faces", action="store_true", help="§12's ICT whole faces instead of §19's")
    parser.add_argument("--report", action="store_true", help="only print the tables of the stored rows")
    args = parser.parse_args()
    if args.whole_faces:
        from landmark_term import CASES

        run_or_report(fit_whole_face, [(case, method) for case in CASES for method in CANDIDATES], WHOLE_FACES,
                      whole_face_report, args.report, key=lambda row: (row["case"], row["method"]))
        return
    if args.in_family:
        from held_out_half import TARGETS

        runs = [(name, half, method) for name in TARGETS for half in HALVES for method in CANDIDATES]
        run_or_report(fit_in_family, runs, IN_FAMILY, in_family_report, args.report,
                      key=lambda row: (row["case"], row["half"], row["method"]))
        return
    runs = [(p, m, s, h, method) for p in args.families for m in args.families for s in range(args.people)
            for h in HALVES for method in CANDIDATES]
    run_or_report(fit_case, runs, RESULTS, report, args.report,
                  key=lambda row: (row["people"], row["model"], row["seed"], row["half"], row["method"]))


if __name__ == "__main__":
    main()
