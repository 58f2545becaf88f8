"""Blending the default's fit with `laplacian`'s, instead of choosing one (issue 37, part 3; docs/studies.md §25).

Where a model cannot make the person, the register default's fallback (§23) returns `laplacian`'s fit
in place of its own. Neither fit is right on every case, and their errors differ in kind (the default
keeps to the model's people, `laplacian` bends towards the data), so a vertex-wise blend
``(1 − w) · default + w · laplacian`` might guess the unseen half better than either. This measures
it on §19's 72 cross-family half faces with landmarks (studies/cross_family_landmarks.py: its cases,
its score): the default without its fallback and `laplacian`, both fitted to the seen half, then each
blend w ∈ {0, ¼, ½, ¾, 1} scored by the held-out half's mean distance to the blended surface (mm).
The shipped gate's decision per case (fired: `laplacian`) is the stored row of
studies/results/default_fallback.json; rules that blend are compared with it.

    python studies/fit_blend.py            # 72 × 2 fits, two at a time; ~6 min on 2 cores
    python studies/fit_blend.py --report   # the tables of the stored rows
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results"
ROWS = RESULTS / "fit_blend.json"
GATE = RESULTS / "default_fallback.json"         # the shipped gate's decisions (§23)
LANDMARKS = RESULTS / "cross_family_landmarks.json"  # the landmark-placed mean's rows (§19)
WEIGHTS = (0.0, 0.25, 0.5, 0.75, 1.0)             # of `laplacian`'s fit


def runs() -> list[tuple]:
    """§19's cases: (people, model, seed, half), as the gate's stored rows list them."""
    return [(r["people"], r["model"], r["seed"], r["half"]) for r in json.loads(GATE.read_text()) if r["set"] == "§19"]


def run_case(people: str, model_family: str, seed: int, half: str) -> dict:
    """Both fits of one case and the held-out and seen distances (mm) of each blend."""
    import torch

    torch.set_num_threads(1)
    from cross_family_landmarks import case_data, inside_distance
    from families import landmarked_model
    from statfit.core.threads import flush_denormals_everywhere
    from statfit.registration.job import register

    flush_denormals_everywhere()
    data = case_data(people, seed, half)
    model = landmarked_model(model_family)
    default = register(model, data["seen"], "default", landmarks=data["landmarks"], threads=1, fallback=False)
    laplacian = register(model, data["seen"], "laplacian", landmarks=data["landmarks"], threads=1)
    row = {"people": people, "model": model_family, "seed": seed, "half": half,
           "seconds": [default.seconds, laplacian.seconds]}
    for w in WEIGHTS:
        vertices = (1 - w) * default.vertices + w * laplacian.vertices
        row[f"held_{w}"] = float(np.nanmean(inside_distance(data["held"], vertices, model.faces)))
        row[f"seen_{w}"] = float(np.nanmean(inside_distance(data["seen"].points, vertices, model.faces)))
    return row


def key(row: dict) -> tuple:
    return (row["people"], row["model"], row["seed"], row["half"])


def report(rows: list[dict]) -> str:
    gate = {key(r): r for r in json.loads(GATE.read_text()) if r["set"] == "§19"}
    mean = {key(r): r["held"] for r in json.loads(LANDMARKS.read_text()) if r.get("method") == "mean" and "held" in r}
    cases = [r for r in rows if key(r) in gate and key(r) in mean]
    fired = {key(r): bool(gate[key(r)]["fallback"]["used"]) for r in cases}
    rules = {f"blend {w:g}": (lambda r, w=w: r[f"held_{w}"]) for w in WEIGHTS}
    rules |= {"gate (shipped)": lambda r: r["held_1.0"] if fired[key(r)] else r["held_0.0"],
              "gate, else blend ¼": lambda r: r["held_1.0"] if fired[key(r)] else r["held_0.25"],
              "gate → blend ¾, else 0": lambda r: r["held_0.75"] if fired[key(r)] else r["held_0.0"]}
    reproduced = sum(abs(rules["gate (shipped)"](r) - gate[key(r)]["held"]) <= 1e-6 * gate[key(r)]["held"]
                     for r in cases)
    lines = [f"§19's cases: mean held-out distance (mm) of each blend (w: `laplacian`'s weight; 0 is the default "
             f"without its fallback, 1 `laplacian`) and of rules that blend where the shipped gate does or does "
             f"not fire. The gate's rule reproduces its stored fit on {reproduced} of {len(cases)} cases.", "",
             "| people | model | cases | mean (no fit) | " + " | ".join(rules) + " |",
             "|---|---|---|---|" + "---|" * len(rules)]
    pairs = sorted({key(r)[:2] for r in cases})
    for pair in pairs:
        group = [r for r in cases if key(r)[:2] == pair]
        lines.append(f"| {pair[0]} | {pair[1]} | {len(group)} | {np.mean([mean[key(r)] for r in group]):.2f} | "
                     + " | ".join(f"{np.mean([rule(r) for r in group]):.2f}" for rule in rules.values()) + " |")
    lines.append(f"| all | all | {len(cases)} | {np.mean([mean[key(r)] for r in cases]):.2f} | "
                 + " | ".join(f"**{np.mean([rule(r) for r in cases]):.3f}**" for rule in rules.values()) + " |")
    lines.append("| cases > 1.1 × mean | | | | " + " | ".join(
        str(sum(rule(r) > 1.1 * mean[key(r)] for r in cases)) for rule in rules.values()) + " |")
    lines.append("| pairs ≤ the better of blend 0 and blend 1 | | | | " + " | ".join(str(sum(
        np.mean([rule(r) for r in cases if key(r)[:2] == p])
        <= min(np.mean([r["held_0.0"] for r in cases if key(r)[:2] == p]),
               np.mean([r["held_1.0"] for r in cases if key(r)[:2] == p])) + 1e-9 for p in pairs))
        for rule in rules.values()) + " |")
    better = np.array([r["held_1.0"] < r["held_0.0"] for r in cases])
    signals = {"the gate's code": [gate[key(r)]["fallback"]["code"] for r in cases],
               "the gate's residual": [gate[key(r)]["fallback"]["residual"] for r in cases],
               "seen-half distance, default ÷ `laplacian`": [r["seen_0.0"] / r["seen_1.0"] for r in cases]}
    lines += ["", f"AUC for \"`laplacian` guesses the held-out half better\" ({better.sum()} of {len(cases)} cases): "
              + "; ".join(f"{name} {_auc(np.array(values), better):.2f}" for name, values in signals.items()) + "."]
    return "\n".join(lines)


def _auc(score: np.ndarray, positive: np.ndarray) -> float:
    """The chance that a positive case scores above a negative one (ties count half)."""
    above = score[positive][:, None] - score[~positive][None, :]
    return float(np.mean((above > 0) + 0.5 * (above == 0)))


if __name__ == "__main__":
    study_main(__doc__, run_case, runs, ROWS, report, key)
