"""The render fit's visibility reused in the fit's stages only, the alignment refreshing every call
(docs/studies.md §31): §26's every-K and §27's movement rule, with
``statfit.render.visibility.VISIBILITY_IN_ALIGNMENT`` off.

§26 and §27 reused the visibility in the alignment too, where the body fits move limbs through the
map's outlines for all their steps; bodies ended 16% closer under every-4 and 15% further under the
1 px rule. This separates the stages. The cases are §27's (ICT's jaw-open and smile at 512², the four
ICT rendering-study cases at 256², §18's cross-family cases at 256², the body study's twelve views at
384²); the rows refreshing every call are §27's own (studies/results/visibility_moved.json, same
bits), so only the reused fits run here. Then the shipped rule on people nothing was chosen on
(``FRESH``), with their own floor. One thread a fit, two fits side by side.

    python studies/visibility_fit_only.py            # ~30 min on 2 cores
    python studies/visibility_fit_only.py --report
"""
from __future__ import annotations

import json
import sys
from pathlib import Path
from unittest import mock

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from adaptive_choice import single_threaded  # noqa: E402
from alignment_settle import FAMILIES, SETS, _fit  # noqa: E402
from render_sensitivity import NUDGE, nudging  # noqa: E402
from study_runs import study_main  # noqa: E402
from visibility_moved import counted_refreshes  # noqa: E402
from visibility_reuse import CHOSEN, UNITS, _chosen  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "visibility_fit_only.json"
EVERY_CALL = ROOT / "studies" / "results" / "visibility_moved.json"
RULES = {"moved-1px": (16, 1.0), "every-4": (4, None),   # (calls per refresh at most, pixels moved)
         "every-call": (1, None), "every-call-nudged": (1, None)}
# People none of the above chose or checked anything on: §18's families with two more seeds each, two more
# bodies; each fitted every call, with the shipped rule, and every call with the map nudged as §28 does
# (the floor of these cases).
FRESH = {"cross-fresh": tuple(f"{p}/{m}/{s}" for p in FAMILIES for m in FAMILIES for s in (2, 3)),
         "body-fresh": tuple(f"{seed}/{yaw:g}" for seed in (7, 8) for yaw in (30.0, -60.0))}
SHIPPED = "every-4"


def fit(case_set: str, case: str, rule: str) -> dict:
    """One case's default fit with ``rule``'s reuse in the fit's stages, the alignment every call."""
    single_threaded()
    import statfit.render.job as job
    import statfit.render.visibility as visibility

    every, moved = RULES[rule]
    with mock.patch.object(visibility, "VISIBILITY_EVERY", every), \
            mock.patch.object(visibility, "VISIBILITY_MOVED", moved), \
            mock.patch.object(visibility, "VISIBILITY_IN_ALIGNMENT", False), counted_refreshes() as calls, \
            nudging(job, NUDGE if rule.endswith("-nudged") else 0.0):
        row = _chosen(case, job) if case_set == "chosen" else _fit(case_set.removesuffix("-fresh"), case, job)
    return {"set": case_set, "case": case, "rule": rule} | row | {"refreshed": calls["refreshes"] / calls["calls"]}


def runs() -> list[tuple]:
    checked = [(s, c, rule) for rule in ("moved-1px", "every-4") for s, cases in ({"chosen": CHOSEN} | SETS).items()
               for c in cases]
    return checked + [(s, c, rule) for s, cases in FRESH.items() for c in cases
                      for rule in ("every-call", SHIPPED, "every-call-nudged")]


def report(rows: list[dict]) -> str:
    base = {(r["set"], r["case"]): r for r in json.loads(EVERY_CALL.read_text()) if r["moved"] is None}
    base |= {(r["set"], r["case"]): r for r in rows if r["rule"] == "every-call"}
    by = {(r["set"], r["case"], r["rule"]): r for r in rows}
    lines = ["| cases | error unit | rule | error, every call | error, reused | reused ÷ every call: mean "
             "(range) | mean \\|ratio − 1\\| | worse by > 2% | calls refreshed | "
             "fit s (sum), every call → reused |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for rule in ("moved-1px", "every-4", "every-call-nudged"):
        for case_set, cases in ({"chosen": CHOSEN} | SETS | FRESH).items():
            both = [c for c in cases if (case_set, c) in base and (case_set, c, rule) in by]
            if not both:
                continue
            old, new = [base[(case_set, c)] for c in both], [by[(case_set, c, rule)] for c in both]
            ratio = np.array([n["error"] / o["error"] for o, n in zip(old, new)])
            unit, mean = UNITS[case_set.removesuffix("-fresh")], lambda rows, key: np.mean([r[key] for r in rows])
            lines.append(
                f"| {case_set} ({len(both)}) | {unit} | {rule} | {mean(old, 'error'):.4g} | {mean(new, 'error'):.4g} | "
                f"{ratio.mean():.3f} ({ratio.min():.3f}–{ratio.max():.3f}) | {np.abs(ratio - 1).mean():.3f} | "
                f"{int((ratio > 1.02).sum())} | {mean(new, 'refreshed'):.2f} | "
                f"{sum(r['seconds'] for r in old):.0f} → {sum(r['seconds'] for r in new):.0f} |")
    lines += ["", "Per case (reused ÷ every call, error): " + "; ".join(
        f"{k[0]} {k[1]} {k[2]} {by[k]['error'] / base[k[:2]]['error']:.3f}"
        for k in by if k[:2] in base and k[2] != "every-call")]
    return "\n".join(lines)


if __name__ == "__main__":
    study_main(__doc__, fit, runs, RESULTS, report, key=lambda r: (r["set"], r["case"], r["rule"]))
