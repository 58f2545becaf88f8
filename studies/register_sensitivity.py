"""How far a registration's held-out error moves for nothing (docs/studies.md §29): §19's cross-family
held-out-half cases fitted with `register`'s default twice, the seen half's scan points as given and
nudged by a Gaussian of σ = 1e-4 mm (a tenth of a micrometre, far below any scanner's noise). What
that moves is the floor under which issue 37's per-case targets cannot tell a change from chance.

3 families × 3 models × 2 people × 4 halves, with the seen half's landmarks (studies/cross_family_landmarks.py);
one thread a fit, two fits side by side; ``held`` in mm.

    python studies/register_sensitivity.py            # ~10 min on 2 cores
    python studies/register_sensitivity.py --report
"""
from __future__ import annotations

import contextlib
import sys
from pathlib import Path
from unittest import mock

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import cross_family_landmarks as protocol  # noqa: E402
from families import LANDMARKED  # noqa: E402
from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "register_sensitivity.json"
NUDGE_MM = 1e-4


def fit(people: str, model_family: str, seed: int, half: str, nudge: float) -> dict:
    """One held-out-half case fitted with the default, its seen points nudged by ``nudge`` mm (0: as given)."""
    from statfit.structures.scan import Scan

    given = protocol.case_data

    def nudged(*args) -> dict:
        data = given(*args)
        points = data["seen"].points
        noise = np.random.default_rng(1).standard_normal(points.shape) * nudge
        return data | {"seen": Scan(points + noise, data["seen"].normals)}

    with mock.patch.object(protocol, "case_data", nudged) if nudge else contextlib.nullcontext():
        return protocol.fit_case(people, model_family, seed, half, "default") | {"nudge": nudge}


def runs() -> list[tuple]:
    from families import build_all, landmarked_model

    build_all(list(LANDMARKED), 2)
    for family in LANDMARKED:
        landmarked_model(family)
    return [(p, m, s, h, nudge) for p in LANDMARKED for m in LANDMARKED for s in range(2) for h in protocol.HALVES
            for nudge in (0.0, NUDGE_MM)]


def report(rows: list[dict]) -> str:
    key = lambda r: (r["people"], r["model"], r["seed"], r["half"])  # noqa: E731
    given = {key(r): r for r in rows if r["nudge"] == 0.0 and "held" in r}
    nudged = {key(r): r for r in rows if r["nudge"] == NUDGE_MM and "held" in r}
    lines = ["| people | model | cases | held, as given (mm) | held, nudged (mm) | nudged ÷ as given: mean (range) | "
             "mean \\|ratio − 1\\| | moved by > 2% | by > 10% |", "|---|---|---|---|---|---|---|---|---|"]
    everything = []
    for people in LANDMARKED:
        for model in LANDMARKED:
            both = [k for k in given if k[:2] == (people, model) and k in nudged]
            if not both:
                continue
            ratio = np.array([nudged[k]["held"] / given[k]["held"] for k in both])
            everything.extend(ratio)
            lines.append(f"| {people} | {model} | {len(both)} | {np.mean([given[k]['held'] for k in both]):.3f} | "
                         f"{np.mean([nudged[k]['held'] for k in both]):.3f} | {ratio.mean():.3f} "
                         f"({ratio.min():.3f}–{ratio.max():.3f}) | {np.abs(ratio - 1).mean():.3f} | "
                         f"{int((np.abs(ratio - 1) > 0.02).sum())} | {int((np.abs(ratio - 1) > 0.1).sum())} |")
    ratio = np.array(everything)
    if len(ratio):
        lines.append(f"| all | | {len(ratio)} | | | {ratio.mean():.3f} ({ratio.min():.3f}–{ratio.max():.3f}) | "
                     f"{np.abs(ratio - 1).mean():.3f} | {int((np.abs(ratio - 1) > 0.02).sum())} | "
                     f"{int((np.abs(ratio - 1) > 0.1).sum())} |")
    failed = [r for r in rows if "error" in r]
    if failed:
        lines += ["", f"{len(failed)} fits refused or failed: " + "; ".join(
            f"{r['people']}/{r['model']}/{r['seed']}/{r['half']} {r['error']}" for r in failed)]
    return "\n".join(lines)


if __name__ == "__main__":
    study_main(__doc__, fit, runs, RESULTS, report,
               key=lambda r: (r["people"], r["model"], r["seed"], r["half"], r["nudge"]))
