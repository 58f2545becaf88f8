"""What else a default fit says about a person outside the model's span (issue 37, part 3; docs/studies.md
§24): signals beside §23's residual, on the same cases, against when `laplacian` guesses better.

§23's fallback needs the fit to leave the scan far away. Where the default loses to `laplacian` with
a residual inside the in-family range (most such cases), the person may still lie outside the span,
which the fit shows in other ways. Each case of studies/default_fallback.py (§15, §12, §9 in family;
§19, §17 across families) is refitted with the default (``fallback=False``, the same fit) and scored:

- ``residual``: §23's (mean distance of the fitted points to the fit, posed model radii);
- ``off_span``: RMS over the vertices of the fit's distance from the model's span (its least-squares
  code's residual, :func:`statfit.model.params.project`), in model radii: how far the hybrid steps
  moved it beyond what the modes make;
- ``code``: the RMS of the fit's coefficients (standard deviations): how unusual a person of the
  model it is;
- ``landmarks_seen``: the share of the model's inner landmarks (17–67; §15's model has only those) whose fitted vertex lies
  within three median point spacings of a scan point: a whole face ~1, half a face ~0.5.

Each is set against the stored errors of the default and `laplacian` (AUC for "`laplacian` better";
the rule "fall back where the signal exceeds τ", τ chosen on the in-family sets as §23's was).

    python studies/span_signals.py            # 163 fits, two at a time; ~8 min on 2 cores
    python studies/span_signals.py --report   # the tables from the stored rows
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from default_fallback import CROSS_FAMILY, ERROR, IN_FAMILY, row_key, stored  # noqa: E402
import default_fallback  # noqa: E402
from study_runs import study_main  # noqa: E402

ROWS = ROOT / "studies" / "results" / "span_signals.json"
INNER = slice(17, 68)
SIGNALS = ("residual", "off_span", "code", "landmarks_seen")


def signals(model, points: np.ndarray, result) -> dict:
    """The fit's signals (module docstring) from its model, the scan points it was given (M, 3) and
    its result."""
    from scipy.spatial import cKDTree

    from statfit.model.params import project
    from statfit.structures.frame import Frame

    radius = Frame.of(model.template).scale
    projection = project(model, result.vertices, result.transform)
    out = {"residual": result.fallback["residual"] if result.fallback else float("nan"),
           "off_span": float(np.sqrt(np.mean(projection.off_span ** 2)) / radius),
           "code": float(np.sqrt(np.mean(projection.coefficients ** 2)))}
    if model.landmarks is not None:     # the 68 of Multi-PIE, or (§15's model) its 51 inner ones
        inner = model.landmarks[INNER] if len(model.landmarks) >= 68 else model.landmarks
        tree = cKDTree(points)
        spacing = float(np.median(tree.query(points, k=2)[0][:, 1]))
        distance, _ = tree.query(result.vertices[inner])
        out["landmarks_seen"] = float(np.mean(distance < 3.0 * spacing))
    return out


def run_case(name: str, *key) -> dict:
    """The set's own default fit (studies/default_fallback.py ``run_case``), its register call
    watched: the row keeps the case's key and adds the signals of the default's fit."""
    import statfit.registration.job as job
    from statfit.core.methods import Fallback
    from statfit.structures.scan import Scan

    seen: dict = {}
    register = job.register

    def watched(model, points, *args, **options):
        """The default's own fit whatever its residual (a fallback that reports and never fires)."""
        result = register(model, points, *args, **options, fallback=Fallback("laplacian", float("inf")))
        seen.update(model=model, points=points.points if isinstance(points, Scan) else np.asarray(points),
                    result=result)
        return result

    job.register = watched      # the studies' case functions import it from the module when they fit
    try:
        row = default_fallback.run_case(name, *key)
    finally:
        job.register = register
    return {**{k: v for k, v in row.items() if k in ("set", "people", "model", "seed", "half", "case", "k")},
            **signals(seen["model"], seen["points"], seen["result"])}


def runs() -> list[tuple]:
    """default_fallback's runs without §8 (its rows keep no case's fit to score)."""
    return [run for run in default_fallback.runs() if run[0] != "§8"]


def cases(rows: list[dict]) -> dict:
    """set → list of (signals, default's error, `laplacian`'s error)."""
    out: dict = {}
    for name in (*IN_FAMILY, *CROSS_FAMILY):
        old = stored(name)
        for row in rows:
            if row["set"] != name:
                continue
            key = row_key(row)[1:]
            if (key, "default") in old:
                out.setdefault(name, []).append((row, old[(key, "default")][ERROR[name]],
                                                 old[(key, "laplacian")][ERROR[name]]))
    return out


def auc(triples: list, signal: str) -> float:
    scored = [(row[signal], lap < default) for row, default, lap in triples if np.isfinite(row.get(signal, np.nan))]
    better = np.array([s for s, flag in scored if flag])
    worse = np.array([s for s, flag in scored if not flag])
    if not better.size or not worse.size:
        return float("nan")
    return float(((better[:, None] > worse[None, :]) + 0.5 * (better[:, None] == worse[None, :])).mean())


def report(rows: list[dict]) -> str:
    sets = cases(rows)
    lines = ["Each signal's range per set, and its AUC for \"`laplacian` guesses better than the default\" "
             "(0.5: no separation; 1: higher means `laplacian` every time; 0: the reverse).", "",
             "| set | cases | laplacian better | " + " | ".join(f"{s}: min – max (AUC)" for s in SIGNALS) + " |",
             "|---|---|---|" + "---|" * len(SIGNALS)]
    for name, triples in sets.items():
        cells = []
        for signal in SIGNALS:
            values = np.array([row.get(signal, np.nan) for row, _, _ in triples], dtype=float)
            values = values[np.isfinite(values)]
            cells.append(f"{values.min():.3g} – {values.max():.3g} ({auc(triples, signal):.2f})" if values.size else "–")
        better = sum(lap < default for _, default, lap in triples)
        lines.append(f"| {name} | {len(triples)} | {better} | " + " | ".join(cells) + " |")
    lines += ["", "The rule \"fall back where the signal exceeds τ\", τ just above its largest in-family value "
              "(as §23 chose the residual's): mean error per set (fired / cases), ÷ the default's.", "",
              "| signal | τ | " + " | ".join(sets) + " |", "|---|---|" + "---|" * len(sets)]
    for signal in ("off_span", "code"):
        inside = [row[signal] for name in IN_FAMILY for row, _, _ in sets.get(name, [])]
        tau = 1.05 * max(inside)
        cells = []
        for triples in sets.values():
            chosen = [lap if row[signal] > tau else default for row, default, lap in triples]
            base = np.mean([default for _, default, _ in triples])
            cells.append(f"{np.mean(chosen):.4g} ({sum(row[signal] > tau for row, _, _ in triples)}/{len(triples)}) "
                         f"{np.mean(chosen) / base:.3f}")
        lines.append(f"| {signal} | {tau:.3g} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    study_main(__doc__, run_case, runs, ROWS, report, row_key)


if __name__ == "__main__":
    main()
