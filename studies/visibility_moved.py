"""The render fit's visibility reused until the mesh moves (docs/studies.md §27): §26's reuse, with a
refresh also whenever a vertex has moved more than ``moved`` pixels since the last one
(``statfit.render.visibility.VISIBILITY_MOVED``; at most ``every`` calls apart,
``VISIBILITY_EVERY``).

Chosen on ICT's jaw-open and smile maps at 512² (benchmarks/cases.py; every call against three
movement limits, timed side by side: the largest limit with both errors within 1% of every call);
checked, the chosen rule against every call, on §22's sets: the four ICT rendering-study cases
(256²), §18's cross-family cases (256²) and the body study's twelve views (384²). One thread a fit,
two fits side by side; the error in each set's unit (studies/alignment_settle.py), the whole fit's
seconds, and the share of the renderer's calls that refreshed.

    python studies/visibility_moved.py            # ~30 min on 2 cores
    python studies/visibility_moved.py --report
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

from adaptive_choice import single_threaded  # noqa: E402
from alignment_settle import SETS, _fit  # noqa: E402
from study_runs import study_main  # noqa: E402
from visibility_reuse import CHOSEN, UNITS, _chosen  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "visibility_moved.json"
EVERY = 16                                   # the longest reuse, whatever the mesh does
CANDIDATES = (0.25, 0.5, 1.0)                # pixels a vertex may move before a refresh
CHECKED = 1.0                                # the choice, checked on the other sets against every call


@contextlib.contextmanager
def counted_refreshes():
    """Inside, the renderer's calls and visibility refreshes are counted: yields {"calls", "refreshes"}."""
    from statfit.renderer.steady import SteadyRenderer

    calls = {"calls": 0, "refreshes": 0}
    call, refresh = SteadyRenderer.__call__, SteadyRenderer._visibility

    def counted_call(self, *args, **kwargs):
        calls["calls"] += 1
        return call(self, *args, **kwargs)

    def counted_refresh(self, *args, **kwargs):
        calls["refreshes"] += 1
        return refresh(self, *args, **kwargs)

    with mock.patch.object(SteadyRenderer, "__call__", counted_call), \
            mock.patch.object(SteadyRenderer, "_visibility", counted_refresh):
        yield calls


def fit(case_set: str, case: str, moved: float | None) -> dict:
    """One case's default fit, refreshing every call (``moved`` None) or reusing the visibility for
    up to ``EVERY`` calls while no vertex moved more than ``moved`` pixels."""
    single_threaded()
    import statfit.render.job as job
    import statfit.render.visibility as visibility

    every = 1 if moved is None else EVERY
    # as measured here: the alignment reused the visibility too (since §31 it refreshes every call)
    with mock.patch.object(visibility, "VISIBILITY_EVERY", every), \
            mock.patch.object(visibility, "VISIBILITY_MOVED", moved), \
            mock.patch.object(visibility, "VISIBILITY_IN_ALIGNMENT", True), counted_refreshes() as calls:
        row = _chosen(case, job) if case_set == "chosen" else _fit(case_set, case, job)
    return {"set": case_set, "case": case, "moved": moved} | row | {"refreshed": calls["refreshes"] / calls["calls"]}


def runs() -> list[tuple]:
    chosen = [("chosen", case, moved) for case in CHOSEN for moved in (None, *CANDIDATES)]
    return chosen + [(s, c, moved) for s, cases in SETS.items() for c in cases for moved in (None, CHECKED)]


def report(rows: list[dict]) -> str:
    by = {(r["set"], r["case"], r["moved"]): r for r in rows}
    lines = ["| cases | error unit | moved (px) | error, every call | error, reused | reused ÷ every call: mean "
             "(range) | worse by > 2% | calls refreshed | fit s (sum), every call → reused |",
             "|---|---|---|---|---|---|---|---|---|"]
    for case_set, cases in ({"chosen": CHOSEN} | SETS).items():
        for moved in CANDIDATES if case_set == "chosen" else (CHECKED,):
            both = [c for c in cases if (case_set, c, None) in by and (case_set, c, moved) in by]
            if not both:
                continue
            base, reused = [by[(case_set, c, None)] for c in both], [by[(case_set, c, moved)] for c in both]
            ratio = np.array([r["error"] / b["error"] for b, r in zip(base, reused)])
            lines.append(
                f"| {case_set} ({len(both)}) | {UNITS[case_set]} | {moved:g} | {np.mean([r['error'] for r in base]):.4g} | "
                f"{np.mean([r['error'] for r in reused]):.4g} | {ratio.mean():.3f} ({ratio.min():.3f}–{ratio.max():.3f}) | "
                f"{int((ratio > 1.02).sum())} | {np.mean([r['refreshed'] for r in reused]):.2f} | "
                f"{sum(r['seconds'] for r in base):.0f} → {sum(r['seconds'] for r in reused):.0f} |")
    lines += ["", "Per case (reused ÷ every call, error): " + "; ".join(
        f"{k[0]} {k[1]} {k[2]:g} px {by[k]['error'] / by[(k[0], k[1], None)]['error']:.3f}"
        for k in by if k[2] is not None and (k[0], k[1], None) in by)]
    return "\n".join(lines)


if __name__ == "__main__":
    study_main(__doc__, fit, runs, RESULTS, report, key=lambda r: (r["set"], r["case"], r["moved"]))
