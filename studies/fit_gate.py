"""A goodness-of-fit gate: fall back to ``laplacian`` where the model cannot explain the scan
(issue 37, part 3; docs/studies.md §21). Measured from stored rows, and (``--in-family-fits``) from
new fits of §12's and §9's in-family cases, whose stored rows have no seen residual.

After the default fit, the gate looks at how far the scan points the fit was given lie from the
fitted surface (``seen``: their mean distance to the fit). If the default cannot explain the scan
it saw (a score above a threshold), the person is taken to be outside what the model spans and the
fit falls back to ``laplacian``; the gate's error on a case is then ``laplacian``'s held-out error,
else the default's. Three scores are compared:

- ``mm``: the default's seen residual in millimetres (a threshold τ in mm: only meaningful for
  head-sized models and scans in mm);
- ``radius``: the same divided by the model's RMS radius (template vertices about their centroid;
  the model's units converted to the scan's by the family's known units, which is what the pose's
  scale gives a fit; ‰): unit-free, and still one fit (the fallback is a second only where it fires);
- ``ratio``: the default's seen residual ÷ ``laplacian``'s (unit-free; both fits always run, so twice
  a fit's time).

Row sets (every ``held``/``seen`` in mm):

- §19, studies/results/cross_family_landmarks.json: a half face with its landmarks, people of one
  family fitted with another's model (72 cases, 9 (people, model) pairs);
- §17, studies/results/cross_family.json: left / right halves without landmarks, the embedded family
  included (the cases the pose search did not refuse for the default or ``laplacian``);
- §15, studies/results/held_out_half.json: ICT people outside ICT's first 50 modes, half faces with
  landmarks (24 cases; in family).

The threshold is also chosen on some families and checked on others: on §19's ICT and mask people
(48 cases), then checked on §19's MakeHuman people, on §17 and on §15; and the other way round.

In family, fitted here (``--in-family-fits``; rows in studies/results/fit_gate_in_family.json; the
gate's error on a case is then the all-vertex error of the method kept):

- §12, studies/landmark_term.py: ICT's first 30 modes, a whole face scan in mm with its 51 landmarks
  (the nose tip 20 mm off), landmark weight 10 (as §20's ``--whole-faces``); all-vertex error in mm;
- §9, studies/register_gauss_newton.py: the full ICT model (100 modes), the registration study's nine
  partial scans, no landmarks; all-vertex error in cm (the study's unit).

Both: ``default`` and ``laplacian`` (tuned presets), one thread, one process, fits in turn; ``seen`` is
the mean distance of the fitted scan points to the fit (:func:`cross_family.inside_distance`, NaN
beyond the fit's open boundary left out), in the scan's units.

    python studies/fit_gate.py --report             # seconds: loads the four models for their radii
    python studies/fit_gate.py --in-family-fits     # 26 fits, ~2–3 min on one core; then the report
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

from adaptive_choice import IN_FAMILY_K, WHOLE_FACE_WEIGHT, single_threaded  # noqa: E402

RESULTS = ROOT / "studies" / "results"
SINGLE_METHODS = ("pca", "statistical", "hybrid", "laplacian", "default")
IN_FAMILY_FAMILY = "ict"
CHOOSE_ON = ("ict", "ict-mask")        # §19's people the threshold is chosen on
IN_FAMILY_FITS = RESULTS / "fit_gate_in_family.json"
GATE_METHODS = ("default", "laplacian")
MM_PER_UNIT = {"mm": 1.0, "cm": 10.0}  # §12's scans are in mm, §9's (ICT's units) in cm
GATE_CHECKS = (("mm", 0.25), ("mm", 0.29), ("mm", 0.76), ("radius", 2.7), ("radius", 3.1), ("radius", 10.0))
VARIANTS = {  # name → (unit, grid shown in the tables, fine grid the threshold is chosen on)
    "mm": ("mm", (0.25, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.1, 1.5, 2.0, 3.0),
           np.round(np.arange(0.10, 5.001, 0.01), 2)),
    "radius": ("‰ of the model's RMS radius", (2.5, 3, 4, 5, 6, 7, 8, 9, 10, 12, 15, 20, 30),
               np.round(np.arange(1.0, 50.001, 0.1), 1)),
    "ratio": ("default seen ÷ laplacian seen", (1.0, 1.1, 1.2, 1.3, 1.4, 1.5, 1.75, 2.0, 2.5, 3.0),
              np.round(np.arange(0.80, 4.001, 0.01), 2)),
}


def model_radius_mm(family: str) -> float:
    """The RMS distance (mm) of the family's template vertices from their centroid."""
    import torch

    torch.set_num_threads(1)
    from families import METRES_PER_UNIT, family_model, landmarked_model, LANDMARKED

    from statfit.structures.frame import Frame

    model = landmarked_model(family) if family in LANDMARKED else family_model(family)
    return Frame.of(np.asarray(model.template, dtype=np.float64)).scale * METRES_PER_UNIT[family] * 1000.0


def cross_family_cases(path: Path) -> list[dict]:
    """§19's or §17's cases: one dict per (people, model, seed, half) that the default and
    ``laplacian`` both fitted: the pair, every stored single method's held-out error, the seen
    residuals of the default and ``laplacian``, and the model family."""
    by = {(r["people"], r["model"], r["seed"], r["half"], r["method"]): r for r in json.loads(path.read_text())
          if "held" in r and "seen" in r}
    keys = sorted({k[:4] for k in by if all((*k[:4], m) in by for m in ("default", "laplacian"))})
    cases = []
    for key in keys:
        held = {m: by[(*key, m)]["held"] for m in (*SINGLE_METHODS, "mean") if (*key, m) in by}
        cases.append({"pair": key[:2], "case": key, "family": key[1], "held": held,
                      "seen": {m: by[(*key, m)]["seen"] for m in ("default", "laplacian")},
                      "seconds": {m: by[(*key, m)]["seconds"] for m in ("default", "laplacian")}})
    return cases


def in_family_cases() -> list[dict]:
    """§15's cases (ICT's first 50 modes), as :func:`cross_family_cases`."""
    rows = [r for r in json.loads((RESULTS / "held_out_half.json").read_text())
            if "case" in r and r.get("k") == IN_FAMILY_K]
    by = {(r["case"], r["half"], r["method"]): r for r in rows}
    keys = sorted({k[:2] for k in by if all((*k[:2], m) in by for m in ("default", "laplacian"))})
    return [{"pair": ("ict (50 modes)", "ict"), "case": key, "family": IN_FAMILY_FAMILY,
             "held": {m: by[(*key, m)]["held"] for m in (*SINGLE_METHODS, "mean") if (*key, m) in by},
             "seen": {m: by[(*key, m)]["seen"] for m in ("default", "laplacian")},
             "seconds": {m: by[(*key, m)]["seconds"] for m in ("default", "laplacian")}} for key in keys]


def score(case: dict, variant: str, radii: dict) -> float:
    seen = case["seen"]
    if variant == "mm":
        return seen["default"]
    if variant == "radius":
        return 1000.0 * seen["default"] / radii[case["family"]]
    return seen["default"] / seen["laplacian"]


def gated(case: dict, variant: str, threshold: float, radii: dict) -> tuple[float, bool]:
    """The gate's held-out error on ``case`` and whether it fell back to ``laplacian``."""
    fires = score(case, variant, radii) > threshold
    return case["held"]["laplacian" if fires else "default"], fires


def mean_gate(cases: list[dict], variant: str, threshold: float, radii: dict) -> tuple[float, int]:
    results = [gated(c, variant, threshold, radii) for c in cases]
    return float(np.mean([r[0] for r in results])), int(sum(r[1] for r in results))


def fixed(cases: list[dict], method: str) -> float:
    return float(np.mean([c["held"][method] for c in cases]))


def time_ratio(cases: list[dict], variant: str, threshold: float, radii: dict) -> float:
    """The gate's fitting time ÷ the default's, from the stored seconds: the default, plus
    ``laplacian`` where the gate fires (``ratio``: always, as it needs both seen residuals)."""
    extra = [c["seconds"]["laplacian"] if variant == "ratio" or gated(c, variant, threshold, radii)[1] else 0.0
             for c in cases]
    default = [c["seconds"]["default"] for c in cases]
    return float((np.sum(default) + np.sum(extra)) / np.sum(default))


def oracle(cases: list[dict]) -> float:
    return float(np.mean([min(c["held"]["default"], c["held"]["laplacian"]) for c in cases]))


def choose(cases: list[dict], variant: str, radii: dict) -> float:
    """The threshold of the variant's fine grid with the lowest mean gated error on ``cases``; of a
    run of equal minima, its middle."""
    grid = VARIANTS[variant][2]
    values = np.array([mean_gate(cases, variant, t, radii)[0] for t in grid])
    best = np.flatnonzero(values <= values.min() + 1e-12)
    return float(grid[best[len(best) // 2]])


def auc(cases: list[dict], variant: str, radii: dict) -> float:
    """How often a case where ``laplacian`` is better scores above one where the default is (ties
    half): 0.5 is no separation, 1 perfect."""
    scores = np.array([score(c, variant, radii) for c in cases])
    lap = np.array([c["held"]["laplacian"] < c["held"]["default"] for c in cases])
    a, b = scores[lap][:, None], scores[~lap][None, :]
    return float(((a > b) + 0.5 * (a == b)).mean()) if lap.any() and (~lap).any() else float("nan")


def weighted_auc(cases: list[dict], variant: str, radii: dict) -> float:
    """:func:`auc` with each pair weighted by the mm at stake in both cases (|default − laplacian|)."""
    scores = np.array([score(c, variant, radii) for c in cases])
    gain = np.array([c["held"]["default"] - c["held"]["laplacian"] for c in cases])
    lap = gain > 0
    a, b = scores[lap][:, None], scores[~lap][None, :]
    weight = np.abs(gain[lap])[:, None] * np.abs(gain[~lap])[None, :]
    return float((weight * ((a > b) + 0.5 * (a == b))).sum() / weight.sum())


def best_single(cases: list[dict]) -> tuple[str, float]:
    means = {m: fixed(cases, m) for m in SINGLE_METHODS if all(m in c["held"] for c in cases)}
    name = min(means, key=means.get)
    return name, means[name]


def by_pair(cases: list[dict]) -> dict:
    pairs: dict = {}
    for c in cases:
        pairs.setdefault(c["pair"], []).append(c)
    return pairs


def conditions(sets: dict, variant: str, threshold: float, radii: dict) -> dict:
    """Issue 37's checks for one threshold: how many §19 pairs are at or below their best single
    method (and within 2% of it), §19 as a whole against the best fixed method over all its cases,
    §15 within 2% of the default, §17 not worse than the default."""
    pairs = by_pair(sets["§19"])
    ratios = [mean_gate(cs, variant, threshold, radii)[0] / best_single(cs)[1] for cs in pairs.values()]
    g19 = mean_gate(sets["§19"], variant, threshold, radii)[0]
    g15, fires15 = mean_gate(sets["§15"], variant, threshold, radii)
    g17 = mean_gate(sets["§17"], variant, threshold, radii)[0]
    return {"at_best": sum(r <= 1 + 1e-9 for r in ratios), "near_best": sum(r <= 1.02 for r in ratios),
            "worst_pair": max(ratios), "n_pairs": len(pairs), "g19": g19, "g15": g15, "g17": g17,
            "fires15": fires15, "all19": g19 <= best_single(sets["§19"])[1] + 1e-9,
            "in_family": g15 <= 1.02 * fixed(sets["§15"], "default"),
            "no_landmarks": g17 <= fixed(sets["§17"], "default")}


def runs_of(grid: np.ndarray, keep: list[bool]) -> list[tuple[float, float]]:
    """The contiguous runs (first, last) of ``grid`` where ``keep`` holds."""
    runs, start = [], None
    for i, k in enumerate(keep):
        if k and start is None:
            start = i
        if start is not None and (not k or i == len(keep) - 1):
            runs.append((float(grid[start]), float(grid[i if k else i - 1])))
            start = None
    return runs


def sweep_table(sets: dict, variant: str, radii: dict) -> list[str]:
    unit, grid, _ = VARIANTS[variant]
    ict = [c for c in sets["§19"] if c["pair"][0] in CHOOSE_ON]
    mh = [c for c in sets["§19"] if c["pair"][0] not in CHOOSE_ON]
    s15, s17 = sets["§15"], sets["§17"]
    lines = [f"**{variant}** (threshold in {unit}): mean held-out error (mm), (gate fired / cases); the "
             "checks: §19 pairs at or below their best single method, §15 ≤ 1.02 × default, §17 ≤ default.", "",
             "| threshold | §19 all | §19 ICT + mask people | §19 MakeHuman people | §17 | §15 | §19 pairs ≤ best | "
             "§15 ≤ 1.02× | §17 ≤ default |", "|---|---|---|---|---|---|---|---|---|"]
    base = {name: (fixed(cs, "default"), fixed(cs, "laplacian"), oracle(cs))
            for name, cs in (("all", sets["§19"]), ("ict", ict), ("mh", mh), ("17", s17), ("15", s15))}
    for label, index in (("default (never fires)", 0), ("laplacian (always)", 1), ("better of the two per case", 2)):
        lines.append(f"| {label} | " + " | ".join(f"{base[k][index]:.2f}" for k in ("all", "ict", "mh", "17", "15"))
                     + " | | | |")
    for threshold in grid:
        cells = []
        for cs in (sets["§19"], ict, mh, s17, s15):
            value, fires = mean_gate(cs, variant, threshold, radii)
            cells.append(f"{value:.2f} ({fires}/{len(cs)})")
        check = conditions(sets, variant, threshold, radii)
        lines.append(f"| {threshold:g} | " + " | ".join(cells) + f" | {check['at_best']}/{check['n_pairs']} | "
                     f"{'yes' if check['in_family'] else 'no'} ({check['g15'] / base['15'][0]:.3f}) | "
                     f"{'yes' if check['no_landmarks'] else 'no'} ({check['g17'] / base['17'][0]:.3f}) |")
    return lines


def pair_table(cases: list[dict], variant: str, threshold: float, radii: dict, title: str) -> list[str]:
    lines = [f"{title}: {variant} gate at {threshold:g}; mean held-out error (mm).", "",
             "| people | model | cases | default | laplacian | best single method | gate | gate ÷ best | "
             "fires | better of the two per case |", "|---|---|---|---|---|---|---|---|---|---|"]
    groups = list(by_pair(cases).items()) + [(("all", "all"), cases)]
    for (people, model), cs in groups:
        name, best = best_single(cs)
        value, fires = mean_gate(cs, variant, threshold, radii)
        lines.append(f"| {people} | {model} | {len(cs)} | {fixed(cs, 'default'):.2f} | {fixed(cs, 'laplacian'):.2f} | "
                     f"{best:.2f} ({name}) | {value:.2f} | {value / best:.2f} | {fires}/{len(cs)} | {oracle(cs):.2f} |")
    return lines


def transfer_table(sets: dict, radii: dict) -> list[str]:
    ict = [c for c in sets["§19"] if c["pair"][0] in CHOOSE_ON]
    mh = [c for c in sets["§19"] if c["pair"][0] not in CHOOSE_ON]
    checks = (("§19 ICT + mask people", ict), ("§19 MakeHuman people", mh), ("§17", sets["§17"]), ("§15", sets["§15"]))
    lines = ["Chosen on some families, checked on the others: the threshold with the lowest mean on the "
             "'chosen on' cases; each cell: gate (default / laplacian), mm; the cases it was chosen on in italics; "
             "the gate's fitting time ÷ the default's over the four sets (stored seconds; rough).", "",
             "| variant | chosen on | threshold | " + " | ".join(name for name, _ in checks) + " | time |",
             "|---|---|---|" + "---|" * len(checks) + "---|"]
    for variant in VARIANTS:
        for label, chosen_on in (("ICT + mask people (§19)", ict), ("MakeHuman people (§19)", mh)):
            threshold = choose(chosen_on, variant, radii)
            cells = []
            for _, cs in checks:
                text = f"{mean_gate(cs, variant, threshold, radii)[0]:.2f} ({fixed(cs, 'default'):.2f} / " \
                       f"{fixed(cs, 'laplacian'):.2f})"
                cells.append(f"*{text}*" if cs is chosen_on else text)
            every = [c for _, cs in checks for c in cs]
            lines.append(f"| {variant} | {label} | {threshold:g} | " + " | ".join(cells)
                         + f" | {time_ratio(every, variant, threshold, radii):.2f}× |")
    return lines


def separation_table(sets: dict, radii: dict) -> list[str]:
    lines = ["Which score separates: AUC (a case where `laplacian` is better scoring above one where the "
             "default is; 0.5 none, 1 perfect), the same weighted by the mm at stake; and the lowest mean "
             "any one threshold reaches on each set (in-sample, so a bound), with that threshold.", "",
             "| variant | AUC §19 / §17 / §15 | weighted AUC §19 / §17 / §15 | best mean §19 | best mean §17 | "
             "best mean §15 | one threshold for all three: §19 / §17 / §15 (÷ default) |",
             "|---|---|---|---|---|---|---|"]
    for variant in VARIANTS:
        aucs = " / ".join(f"{auc(sets[s], variant, radii):.2f}" for s in ("§19", "§17", "§15"))
        waucs = " / ".join(f"{weighted_auc(sets[s], variant, radii):.2f}" for s in ("§19", "§17", "§15"))
        bests = []
        for s in ("§19", "§17", "§15"):
            t = choose(sets[s], variant, radii)
            bests.append(f"{mean_gate(sets[s], variant, t, radii)[0]:.2f} (at {t:g})")
        # one threshold for the three sets: the lowest worst ratio to the default over them
        grid = VARIANTS[variant][2]
        worst = [max(mean_gate(sets[s], variant, t, radii)[0] / fixed(sets[s], "default") for s in ("§19", "§17", "§15"))
                 for t in grid]
        t = float(grid[int(np.argmin(worst))])
        joint = " / ".join(f"{mean_gate(sets[s], variant, t, radii)[0] / fixed(sets[s], 'default'):.3f}"
                           for s in ("§19", "§17", "§15"))
        lines.append(f"| {variant} | {aucs} | {waucs} | " + " | ".join(bests) + f" | {joint} (at {t:g}) |")
    return lines


def all_conditions(sets: dict, radii: dict) -> list[str]:
    d15, d17 = fixed(sets["§15"], "default"), fixed(sets["§17"], "default")
    lines = ["Every threshold of each variant's fine grid against issue 37's checks: (a) each §19 pair at or "
             "below its best single method (a′: within 2% of it), (b) §15 ≤ 1.02 × the default, (c) §17 ≤ the "
             "default. Thresholds meeting them (runs of the grid), and at each run's ends: §19 all, §15 ÷ default "
             "(fired / 24), §17 ÷ default, the worst §19 pair ÷ its best method.", "",
             "| variant | (a) alone | (b) alone | (c) alone | (a), (b), (c) | (a′), (b), (c) | at those thresholds |",
             "|---|---|---|---|---|---|---|"]
    for variant, (_, _, grid) in VARIANTS.items():
        checks = [conditions(sets, variant, t, radii) for t in grid]
        strict = runs_of(grid, [c["at_best"] == c["n_pairs"] and c["in_family"] and c["no_landmarks"] for c in checks])
        near = runs_of(grid, [c["near_best"] == c["n_pairs"] and c["in_family"] and c["no_landmarks"] for c in checks])
        ends = []
        for first, last in near:
            for t in sorted({first, last}):
                c = checks[int(np.argmin(np.abs(grid - t)))]
                ends.append(f"{t:g}: {c['g19']:.2f}, {c['g15'] / d15:.3f} ({c['fires15']}/{len(sets['§15'])}), "
                            f"{c['g17'] / d17:.3f}, {c['worst_pair']:.3f}")
        text = lambda rs: ", ".join(f"{a:g}–{b:g}" if a != b else f"{a:g}" for a, b in rs) or "none"  # noqa: E731
        alone = [text(runs_of(grid, [c["at_best"] == c["n_pairs"] for c in checks])),
                 text(runs_of(grid, [c["in_family"] for c in checks])),
                 text(runs_of(grid, [c["no_landmarks"] for c in checks]))]
        lines.append(f"| {variant} | " + " | ".join(alone) + f" | {text(strict)} | {text(near)} | {'; '.join(ends) or '–'} |")
    return lines


def worst_cases(cases: list[dict], variant: str, threshold: float, radii: dict, title: str, count: int = 5) -> list[str]:
    """The cases where the gate loses most against the better of the default and ``laplacian``."""
    lines = [f"{title}: the {count} cases the {variant} gate at {threshold:g} costs most against the better of "
             "the two (mm).", "", "| case | default seen | laplacian seen | score | fires | default held | "
             "laplacian held | cost |", "|---|---|---|---|---|---|---|---|"]
    def cost(c: dict) -> float:
        return gated(c, variant, threshold, radii)[0] - min(c["held"]["default"], c["held"]["laplacian"])
    for c in sorted(cases, key=cost, reverse=True)[:count]:
        lines.append(f"| {' / '.join(map(str, c['case']))} | {c['seen']['default']:.2f} | {c['seen']['laplacian']:.2f} | "
                     f"{score(c, variant, radii):.2f} | {'yes' if gated(c, variant, threshold, radii)[1] else 'no'} | "
                     f"{c['held']['default']:.2f} | {c['held']['laplacian']:.2f} | {cost(c):+.2f} |")
    return lines


def firing_cases(cases: list[dict], variant: str, threshold: float, radii: dict, title: str) -> list[str]:
    lines = [f"{title}: the cases where the {variant} gate at {threshold:g} fires (mm).", "",
             "| case | default seen | laplacian seen | score | default held | laplacian held | change |",
             "|---|---|---|---|---|---|---|"]
    for c in cases:
        value, fires = gated(c, variant, threshold, radii)
        if fires:
            lines.append(f"| {' / '.join(map(str, c['case']))} | {c['seen']['default']:.2f} | "
                         f"{c['seen']['laplacian']:.2f} | {score(c, variant, radii):.2f} | {c['held']['default']:.2f} | "
                         f"{c['held']['laplacian']:.2f} | {c['held']['laplacian'] - c['held']['default']:+.2f} |")
    return lines


def seen_residual(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> tuple[float, float]:
    """The mean distance of the fitted scan points to the fit (§17's and §19's ``seen``), and the share
    of points left out as lying beyond the fit's open boundary."""
    from cross_family import inside_distance

    distance = inside_distance(points, vertices, faces)
    return float(np.nanmean(distance)), float(np.isnan(distance).mean())


def fit_whole_face(case: str, method: str) -> dict:
    """§12's case (studies/landmark_term.py) fitted as §12 and §20 fit it: the whole scan with its
    landmarks at weight 10; the all-vertex error and the seen residual in mm."""
    single_threaded()
    from cases import register_named
    from landmark_term import case_data

    data = case_data(case)
    model = data["model"]
    result = register_named(model, data["points"], method, landmarks=data["landmarks"],
                            landmark_weight=WHOLE_FACE_WEIGHT, threads=1)
    seen, beyond = seen_residual(data["points"], result.vertices, model.faces)
    return {"set": "§12", "case": case, "method": method, "unit": "mm", "seconds": result.seconds,
            "all": float(np.linalg.norm(result.vertices - data["truth"], axis=1).mean()),
            "landmark_mm": float(np.linalg.norm(result.vertices[data["indices"]] - data["truth"][data["indices"]],
                                                axis=1).mean()),
            "seen": seen, "beyond": beyond} | ({"fallback": result.fallback} if result.fallback else {})


def fit_in_span(case: str, method: str) -> dict:
    """§9's case (benchmarks/cases.py ``scan_case``) fitted with the full ICT model, no landmarks;
    the all-vertex error and the seen residual in cm (ICT's units)."""
    single_threaded()
    from cases import ict_model, scan_case
    from statfit.registration.job import register

    data, model = scan_case(case), ict_model()
    result = register(model, data.points, method, threads=1)
    seen, beyond = seen_residual(data.points, result.vertices, model.faces)
    return {"set": "§9", "case": case, "method": method, "unit": "cm", "seconds": result.seconds,
            "all": float(np.linalg.norm(result.vertices - data.target, axis=1).mean()),
            "seen": seen, "beyond": beyond} | ({"fallback": result.fallback} if result.fallback else {})


def in_family_runs() -> list[tuple]:
    from cases import STUDY_SCAN_CASES
    from landmark_term import CASES as WHOLE_FACES

    return ([("§12", case, method) for case in WHOLE_FACES for method in GATE_METHODS]
            + [("§9", case, method) for case in STUDY_SCAN_CASES for method in GATE_METHODS])


def run_in_family_fits() -> None:
    """Every run of :func:`in_family_runs` not yet stored, in turn in this process (one thread), each row
    written to :data:`IN_FAMILY_FITS` as it ends."""
    rows = json.loads(IN_FAMILY_FITS.read_text()) if IN_FAMILY_FITS.is_file() else []
    done = {(r["set"], r["case"], r["method"]) for r in rows}
    todo = [run for run in in_family_runs() if run not in done]
    for count, (name, case, method) in enumerate(todo, 1):
        rows.append((fit_whole_face if name == "§12" else fit_in_span)(case, method))
        IN_FAMILY_FITS.write_text(json.dumps(rows, indent=1))
        row = rows[-1]
        print(f"{count}/{len(todo)} {name} {case} {method}: all {row['all']:.4f} {row['unit']}, "
              f"seen {row['seen']:.4f}, {row['seconds']:.1f} s", flush=True)


def in_family_fit_cases(rows: list[dict]) -> dict:
    """The stored in-family fits as gate cases (:func:`cross_family_cases`' form), by set: ``held`` is
    the all-vertex error (the set's unit), ``seen`` in mm (the gate's τ is in mm)."""
    by = {(r["set"], r["case"], r["method"]): r for r in rows}
    sets: dict = {}
    for name, case in dict.fromkeys(run[:2] for run in in_family_runs()):
        if not all((name, case, m) in by for m in GATE_METHODS):
            continue
        fits = {m: by[(name, case, m)] for m in GATE_METHODS}
        sets.setdefault(name, []).append({
            "pair": ("ict", "ict"), "case": (case,), "family": IN_FAMILY_FAMILY, "unit": fits["default"]["unit"],
            "held": {m: fits[m]["all"] for m in GATE_METHODS},
            "seen": {m: fits[m]["seen"] * MM_PER_UNIT[fits[m]["unit"]] for m in GATE_METHODS},
            "seconds": {m: fits[m]["seconds"] for m in GATE_METHODS}})
    return sets


def in_family_fits_report(radii: dict) -> list[str]:
    """§12's and §9's new fits: per case, and the gate at §21's thresholds."""
    if not IN_FAMILY_FITS.is_file():
        return ["(no in-family fits stored: run `python studies/fit_gate.py --in-family-fits`)"]
    sets = in_family_fit_cases(json.loads(IN_FAMILY_FITS.read_text()))
    radii = {IN_FAMILY_FAMILY: model_radius_mm(IN_FAMILY_FAMILY)} | radii
    radius = radii[IN_FAMILY_FAMILY]
    lines = [f"In family, new fits (§12: whole faces with landmarks, ICT's first 30 modes, error mm; §9: nine "
             f"partial scans, the full ICT model, error cm): seen residual in mm and in ‰ of ICT's RMS radius "
             f"({radius:.1f} mm); all-vertex error of each method.", "",
             "| set | case | default seen mm (‰) | laplacian seen mm | default all | laplacian all | better |",
             "|---|---|---|---|---|---|---|"]
    for name, cases in sets.items():
        for c in cases:
            better = "laplacian" if c["held"]["laplacian"] < c["held"]["default"] else "default"
            lines.append(f"| {name} | {c['case'][0]} | {c['seen']['default']:.3f} ({score(c, 'radius', radii):.2f}) | "
                         f"{c['seen']['laplacian']:.3f} | {c['held']['default']:.4f} | {c['held']['laplacian']:.4f} | "
                         f"{better} |")
    lines += ["", "The gate at §21's thresholds: mean all-vertex error (fired / cases), ÷ the default's.", "",
              "| set (unit) | default | laplacian | better of the two per case | "
              + " | ".join(f"{t:g} {'mm' if v == 'mm' else '‰'}" for v, t in GATE_CHECKS) + " |",
              "|---|---|---|---|" + "---|" * len(GATE_CHECKS)]
    for name, cases in sets.items():
        base = fixed(cases, "default")
        cells = []
        for variant, threshold in GATE_CHECKS:
            value, fires = mean_gate(cases, variant, threshold, radii)
            cells.append(f"{value:.4f} ({fires}/{len(cases)}) {value / base:.3f}")
        lines.append(f"| {name} ({cases[0]['unit']}) | {base:.4f} | {fixed(cases, 'laplacian'):.4f} "
                     f"({fixed(cases, 'laplacian') / base:.3f}) | {oracle(cases):.4f} | " + " | ".join(cells) + " |")
    lines += ["", "The default's seen residual per set (a threshold above the largest fires on none), how often "
              "`laplacian` is better, and AUC for it (as in §21's separation table).", "",
              "| set | default seen mm: min – max | ‰: min – max | laplacian better | AUC mm |", "|---|---|---|---|---|"]
    for name, cases in sets.items():
        mm = [c["seen"]["default"] for c in cases]
        rel = [score(c, "radius", radii) for c in cases]
        lines.append(f"| {name} | {min(mm):.3f} – {max(mm):.3f} | {min(rel):.2f} – {max(rel):.2f} | "
                     f"{sum(c['held']['laplacian'] < c['held']['default'] for c in cases)}/{len(cases)} | "
                     f"{auc(cases, 'mm', radii):.2f} |")
    return lines


def report() -> str:
    sets = {"§19": cross_family_cases(RESULTS / "cross_family_landmarks.json"),
            "§17": cross_family_cases(RESULTS / "cross_family.json"),
            "§15": in_family_cases()}
    families = sorted({c["family"] for cs in sets.values() for c in cs})
    radii = {f: model_radius_mm(f) for f in families}
    ict = [c for c in sets["§19"] if c["pair"][0] in CHOOSE_ON]
    lines = [f"Cases: §19 {len(sets['§19'])}, §17 {len(sets['§17'])}, §15 {len(sets['§15'])}. Model RMS radii (mm): "
             + ", ".join(f"{f} {r:.1f}" for f, r in radii.items()) + ".", ""]
    for variant in VARIANTS:
        lines += sweep_table(sets, variant, radii) + [""]
    lines += transfer_table(sets, radii) + [""]
    lines += separation_table(sets, radii) + [""]
    lines += all_conditions(sets, radii) + [""]
    for variant in ("mm", "radius"):
        threshold = choose(ict, variant, radii)
        lines += pair_table(sets["§19"], variant, threshold, radii, "§19 (landmarks), per pair, chosen on ICT + mask people")
        lines += [""] + pair_table(sets["§17"], variant, threshold, radii, "§17 (no landmarks), per pair") + [""]
        lines += firing_cases(sets["§15"], variant, threshold, radii, "§15 (in family)") + [""]
        for name in ("§19", "§17"):
            lines += worst_cases(sets[name], variant, threshold, radii, name) + [""]
    lines += pair_table(sets["§19"], "mm", 0.6, radii, "§19, per pair, at the first probe's τ") + [""]
    lines += pair_table(sets["§19"], "mm", 1.1, radii, "§19, per pair, at the lowest τ that fires on no §15 case") + [""]
    lines += in_family_fits_report(radii) + [""]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--report", action="store_true",
                        help="print the tables from the stored rows (the default without --in-family-fits)")
    parser.add_argument("--in-family-fits", action="store_true",
                        help="first fit §12's and §9's in-family cases not yet stored in "
                             "studies/results/fit_gate_in_family.json (one thread, in turn)")
    args = parser.parse_args()
    if args.in_family_fits and not args.report:
        run_in_family_fits()
    print(report())


if __name__ == "__main__":
    main()
