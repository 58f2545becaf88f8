"""What a fit guesses where it saw nothing, for a person outside the model (issue 11, part 5;
docs/studies.md §15).

Protocol ("a real person is never in the model's span"): the fits use the ICT model truncated to
its first ``--k`` modes (default 50); each target is drawn from all 100 identity modes, plus an
expression outside the identity model, plus a smooth random deformation outside any span (six
Gaussian bumps, 2.9 cm wide, 2 mm standard deviation per axis). A front scan (6,000 points) is split
at the inner landmarks' centroid into halves: left / right (x) and upper / lower (y). Each half is
fitted alone, with the 51 inner landmarks (Multi-PIE 17–67, 1 mm noise) of that half only; the
other half is the test:

- ``held`` mean distance (mm) of the held-out half's scan points to the fitted surface,
- ``held_lm`` mean error (mm) of the held-out half's landmarks,
- ``seen`` mean distance of the fitted half's points (how closely it fits what it sees),
- ``all`` mean all-vertex error (mm).

"mean" is the unfitted model mean placed by the landmark similarity: the bar a fit must beat.
The in-span check runs the registration study's nine cases (docs/studies.md §1: the full model,
identity in span, expression outside) for every pipeline that is not a plain method.

    python studies/held_out_half.py                 # ~50 min on 2 cores; results cached
    python studies/held_out_half.py --report        # tables from studies/results/held_out_half.json
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from cases import FORMER_DEFAULT  # noqa: E402
from default_candidates import register_candidate  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "held_out_half.json"
# seed, expression, weight: seeds apart from the registration study's, expressions from its list
TARGETS = {"A": (201, "jawOpen", 0.7), "B": (202, "mouthSmile_R", 1.0), "C": (203, "browInnerUp_L", 0.9),
           "D": (204, "cheekPuff_L", 1.0), "E": (205, "mouthLeft", 0.8), "F": (206, "eyeBlink_L", 1.0)}
HALVES = ("left", "right", "upper", "lower")
INNER = slice(17, 68)
NOISE_CM = 0.1
BUMPS, BUMP_WIDTH, BUMP_CM = 6, 0.3, 0.2   # width in RMS radii
SCAN_POINTS = 6000
METHODS = ("mean", "default", FORMER_DEFAULT, "statistical", "hybrid", "laplacian", "pca", "regularized", "none")


def candidates() -> dict:
    """Pipelines tried beside the shipped methods: name → (stages, register options)."""
    from statfit.core.settings import Settings

    def gn(noise: float, levels: int = 5) -> Settings:
        return Settings("pca", 200, 0.0, optimizer="gauss-newton", noise=noise, levels=levels)

    from cases import former_default_stages

    tried = {FORMER_DEFAULT: (former_default_stages(), {})}
    for weight in (0.0, 1.0, 10.0):
        for noise in (0.003, 0.01, 0.03):
            tried[f"pca σ {noise} w {weight:g}"] = ((gn(noise),), {"landmark_weight": weight})
        tried[f"laplacian w {weight:g}"] = (None, {"landmark_weight": weight})
        for noise in (0.01, 0.03):
            tried[f"pca σ {noise} → laplacian λ 300 lr 0.03 300 it w {weight:g}"] = (
                (gn(noise), Settings("laplacian", 300, 0.03, lam=300.0)), {"landmark_weight": weight})
            tried[f"pca σ {noise} → statistical β 100 lr 0.01 300 it w {weight:g}"] = (
                (gn(noise), Settings("statistical", 300, 0.01, beta=100.0)), {"landmark_weight": weight})
        tried[f"pca σ 0.003 → hybrid β 1 lr 0.006 200 it w {weight:g}"] = (
            (gn(0.003), Settings("hybrid", 200, 0.006, beta=1.0, lam=19.0)), {"landmark_weight": weight})
    closed_form = replace(gn(0.003), landmarks=False)   # the default's first stage
    for lr in (0.02, 0.03):   # a larger step for the hybrid stage (docs/studies.md §12)
        for weight in (1.0, 3.0, 10.0):
            tried[f"default's closed form → hybrid β 1 lr {lr} 200 it w {weight:g}"] = (
                (closed_form, Settings("hybrid", 200, lr, beta=1.0, lam=19.0)), {"landmark_weight": weight})
    from default_candidates import candidates as cross_family_candidates   # docs/studies.md §19
    return tried | cross_family_candidates()


def smooth_deformation(vertices: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(N, 3) displacement: a sum of Gaussian bumps centred on random vertices."""
    scale = float(np.sqrt(((vertices - vertices.mean(axis=0)) ** 2).sum(axis=1).mean()))
    centres = vertices[rng.choice(len(vertices), BUMPS, replace=False)]
    amplitudes = rng.normal(scale=BUMP_CM, size=(BUMPS, 3))
    d2 = ((vertices[:, None, :] - centres[None]) ** 2).sum(axis=2)
    return np.exp(-d2 / (2 * (BUMP_WIDTH * scale) ** 2)) @ amplitudes


def case_data(name: str, half: str) -> dict:
    """Target, the fitted half's points and landmarks, the held-out half's points and landmarks."""
    from cases import ICT_EXPRESSIONS, ICT_MODEL, ict_model
    from statfit.synth.sample import load_delta, sample_target, scan_from_view

    seed, expression, weight = TARGETS[name]
    rng = np.random.default_rng(seed)
    model = ict_model()
    target = sample_target(model, rng, 1.0, load_delta(str(ICT_EXPRESSIONS), expression), weight)
    target = target + smooth_deformation(target, rng)
    points = scan_from_view(target, model.faces, rng, SCAN_POINTS, 0.0, 0.0)
    indices = np.load(ICT_MODEL)["landmarks68"][INNER].astype(np.int64)
    truth = target[indices]
    noisy = truth + rng.normal(scale=NOISE_CM, size=truth.shape)
    centre = truth.mean(axis=0)
    axis, sign = {"left": (0, 1), "right": (0, -1), "upper": (1, 1), "lower": (1, -1)}[half]
    seen_points = sign * (points[:, axis] - centre[axis]) > 0
    seen_landmarks = sign * (truth[:, axis] - centre[axis]) > 0
    landmarks = np.where(seen_landmarks[:, None], noisy, np.nan)
    return {"target": target, "indices": indices, "truth": truth, "landmarks": landmarks,
            "seen": points[seen_points], "held": points[~seen_points], "held_landmarks": ~seen_landmarks}


def fit(method: str, name: str, half: str, k: int) -> dict:
    import torch

    torch.set_num_threads(1)
    from cases import ict_model
    from statfit.geometry.metrics import surface_distance
    from statfit.model.statmodel import with_landmarks
    from statfit.registration.prealign import landmark_alignment
    from statfit.core.threads import flush_denormals_everywhere

    flush_denormals_everywhere()
    data = case_data(name, half)
    model = with_landmarks(ict_model(), data["indices"]).truncated(k)
    seconds, fallback = 0.0, None
    if method == "mean":
        vertices = landmark_alignment(model, data["landmarks"]).apply(model.template)
    else:
        result = register_candidate(method, model, data["seen"], candidates(), threads=1, landmarks=data["landmarks"])
        vertices, seconds, fallback = result.vertices, result.seconds, result.fallback
    held = data["held_landmarks"]
    mm = 10.0  # ICT is in cm
    return {"method": method, "case": name, "half": half, "k": k, "seconds": seconds,
            "held": mm * float(surface_distance(data["held"], vertices, model.faces).mean()),
            "seen": mm * float(surface_distance(data["seen"], vertices, model.faces).mean()),
            "held_lm": mm * float(np.linalg.norm(vertices[data["indices"][held]] - data["truth"][held], axis=1).mean()),
            "all": mm * float(np.linalg.norm(vertices - data["target"], axis=1).mean())} | (
        {"fallback": fallback} if fallback else {})


def in_span(method: str) -> dict:
    """All-vertex error (cm) on the registration study's nine cases, full model, no landmarks."""
    import torch

    torch.set_num_threads(1)
    from cases import STUDY_SCAN_CASES, ict_model, scan_case
    from statfit.core.threads import flush_denormals_everywhere

    flush_denormals_everywhere()
    errors = {}
    for name in STUDY_SCAN_CASES:
        case = scan_case(name)
        result = register_candidate(method, ict_model(), case.points, candidates(), threads=1, align="none")
        errors[name] = float(np.linalg.norm(result.vertices - case.target, axis=1).mean())
    return {"method": method, "in_span": errors}


def load() -> list[dict]:
    return json.loads(RESULTS.read_text()) if RESULTS.is_file() else []


def run(k: int, methods: list[str], with_in_span: bool) -> None:
    rows = load()
    have = {(r["method"], r.get("case"), r.get("half"), r.get("k")) for r in rows}
    jobs = [(m, c, h, k) for m in methods for c in TARGETS for h in HALVES if (m, c, h, k) not in have]
    span_jobs = [m for m in methods if with_in_span and m != "mean"
                 and not any(r["method"] == m and "in_span" in r for r in rows)]
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        pending = [pool.submit(fit, *job) for job in jobs] + [pool.submit(in_span, m) for m in span_jobs]
        for done, future in enumerate(pending, 1):
            rows.append(future.result())
            RESULTS.write_text(json.dumps(rows, indent=1))
            print(f"{done}/{len(pending)}", rows[-1]["method"], rows[-1].get("case", "in-span"), flush=True)


def report(k: int) -> str:
    saved = load()
    rows = [r for r in saved if r.get("k") == k]
    spans = {r["method"]: r["in_span"] for r in saved if "in_span" in r}
    methods = list(dict.fromkeys(r["method"] for r in rows))
    by = {(r["method"], r["case"], r["half"]): r for r in rows}
    lines = [f"Fitted with the first {k} modes; mm; means over {len(TARGETS)} people × 4 halves "
             "(per half: the held-out point distance).", "",
             "| pipeline | held-out points | ÷ mean's | held-out landmarks | ÷ mean's | fitted points | all vertices | "
             + " | ".join(f"held {h}" for h in HALVES) + " | s per fit | in-span mean (cm) |",
             "|---|---|---|---|---|---|---|" + "---|" * len(HALVES) + "---|---|"]

    def mean(method: str, key: str, halves=HALVES) -> float:
        values = [by[(method, c, h)][key] for c in TARGETS for h in halves if (method, c, h) in by]
        return float(np.mean(values)) if values else float("nan")

    base_held, base_lm = mean("mean", "held"), mean("mean", "held_lm")
    for m in methods:
        span = spans.get(m)
        span_text = f"{np.mean(list(span.values())):.4f}" if span else ""
        lines.append(f"| {m} | {mean(m, 'held'):.3f} | {mean(m, 'held') / base_held:.2f} | {mean(m, 'held_lm'):.3f} | "
                     f"{mean(m, 'held_lm') / base_lm:.2f} | {mean(m, 'seen'):.3f} | {mean(m, 'all'):.3f} | "
                     + " | ".join(f"{mean(m, 'held', (h,)):.3f}" for h in HALVES)
                     + f" | {mean(m, 'seconds'):.1f} | {span_text} |")
    if spans:
        from cases import STUDY_SCAN_CASES
        lines += ["", "In span (the registration study's nine cases, all-vertex error in cm):", "",
                  "| pipeline | " + " | ".join(STUDY_SCAN_CASES) + " | mean |",
                  "|---|" + "---|" * (len(STUDY_SCAN_CASES) + 1)]
        for m, span in spans.items():
            lines.append(f"| {m} | " + " | ".join(f"{span[c]:.3f}" for c in STUDY_SCAN_CASES)
                         + f" | {np.mean(list(span.values())):.4f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--k", type=int, default=50)
    parser.add_argument("--methods", nargs="*", help="methods or candidate names (default: all)")
    parser.add_argument("--no-in-span", action="store_true")
    parser.add_argument("--report", action="store_true")
    args = parser.parse_args()
    if not args.report:
        run(args.k, args.methods or [*METHODS, *candidates()], not args.no_in_span)
    print(report(args.k))


if __name__ == "__main__":
    main()
