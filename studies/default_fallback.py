"""The register default with its fallback to ``laplacian``, on every case of the studies that chose
and checked it (issue 37, part 3; docs/studies.md §23).

The default (closed form, then 200 hybrid steps) now measures, after its fit, how far the scan points
it was given lie from the fitted surface (mean, in the posed model's RMS radii; points beyond the
fit's open boundary left out) and how unusual a person of the model the fitted shape is (the RMS over
the modes of its code, standard deviations); above ``statfit.core.methods.FALLBACK_RESIDUAL`` (2%) or
``FALLBACK_CODE`` (3.5) it refits with ``laplacian`` from the same pose (the code's criterion was found
by studies/span_signals.py). This reruns the shipped default, as a user gets it, on:

- §15 (studies/held_out_half.py): 24 ICT half faces with landmarks, ICT's first 50 modes: in family;
- §12 (studies/landmark_term.py via fit_gate.fit_whole_face): 4 whole faces, 30 modes, landmarks: in family;
- §9 (fit_gate.fit_in_span): the registration study's 9 partial scans, the full ICT model: in family;
- §8 (benchmarks/real_scans.py ``clutter_case``): 18 ICT people with an expression outside the model,
  a range scan in a random pose and unit, without and with clutter (hair, neck, shoulders: 50% of
  the shape's points): in family, the clutter rules on;
- §19 (studies/cross_family_landmarks.py): 72 half faces with landmarks, 3 families × 3 models;
- §17 (studies/cross_family.py): the half scans without landmarks, 4 families (the stored cases).

The thresholds were chosen on the in-family sets (round values above all of theirs); §19 and §17
check them. Each row is the study's own row for method ``default``
with the fallback's report; the report sets it beside the stored rows of the default before the
fallback and of ``laplacian`` (the same fits: a gate that does not fire leaves the default's fit
unchanged to the bit, one that fires returns ``laplacian``'s).

    python studies/default_fallback.py            # ~150 fits, two at a time; ~15 min on 2 cores
    python studies/default_fallback.py --report   # the tables of the stored rows
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
ROWS = RESULTS / "default_fallback.json"
IN_FAMILY = ("§15", "§12", "§9")
CLUTTER = (0.0, 0.5)        # §8's clutter per shape point
CROSS_FAMILY = ("§19", "§17")
STORED = {"§19": RESULTS / "cross_family_landmarks.json", "§17": RESULTS / "cross_family.json",
          "§15": RESULTS / "held_out_half.json", "§12": RESULTS / "fit_gate_in_family.json",
          "§9": RESULTS / "fit_gate_in_family.json", "§8": ROOT / "benchmarks" / "results" / "real_scans_cpu.json"}
IN_FAMILY_K = 50            # §15's modes
ERROR = {"§19": "held", "§17": "held", "§15": "held", "§12": "all", "§9": "all"}
UNIT = {"§19": "mm", "§17": "mm", "§15": "mm", "§12": "mm", "§9": "cm"}


def case_key(name: str, row: dict) -> tuple | None:
    """A stored or new row's case within its set (None: a row of another set or protocol)."""
    if name in ("§19", "§17"):
        return (row["people"], row["model"], row["seed"], row["half"])
    if name == "§15":
        return (row["case"], row["half"]) if "case" in row and row.get("k") == IN_FAMILY_K else None
    return (row["case"],) if row.get("set") == name else None


def stored(name: str) -> dict:
    """(case, method) → the stored row, for every case the default and ``laplacian`` both fitted."""
    rows = [r for r in json.loads(STORED[name].read_text()) if ERROR[name] in r]
    by = {(key, r["method"]): r for r in rows if (key := case_key(name, r)) is not None}
    cases = {key for key, _ in by}
    return {k: v for k, v in by.items() if all((k[0], m) in by for m in ("default", "laplacian"))
            and k[0] in cases}


def runs() -> list[tuple]:
    """(set, *case) for every case of every set that the stored default and ``laplacian`` both fitted,
    and §8's stored default fits."""
    return ([(name, *key) for name in (*IN_FAMILY, *CROSS_FAMILY)
             for key in sorted({key for key, method in stored(name) if method == "default"})]
            + [("§8", seed) for seed in sorted(clutter_stored())])


def clutter_stored() -> dict:
    """§8's stored default rows (benchmarks/results/real_scans_cpu.json) by seed."""
    return {r["seed"]: r for r in json.loads(STORED["§8"].read_text())["clutter"] if r["method"] == "default"}


def run_case(name: str, *key) -> dict:
    """The shipped default on one case, by its study's own function; the row keeps the set's key."""
    if name == "§8":
        from real_scans import clutter_case

        return {"set": name, **clutter_case(*key, "default")}
    if name == "§19":
        from cross_family_landmarks import fit_case

        row = fit_case(*key, "default")
    elif name == "§17":
        from cross_family import fit_case

        row = fit_case(*key, "default")
    elif name == "§15":
        from held_out_half import fit

        row = fit("default", *key, IN_FAMILY_K)
    else:
        from fit_gate import fit_in_span, fit_whole_face

        row = (fit_whole_face if name == "§12" else fit_in_span)(key[0], "default")
    return {"set": name, **row}


def row_key(row: dict) -> tuple:
    name = row["set"]
    if name == "§8":
        return (name, row["seed"])
    return (name, *case_key(name, {**row, "set": name, "k": IN_FAMILY_K}))


def report(rows: list[dict]) -> str:
    lines = ["Per set: the stored default (before the fallback), stored `laplacian`, the shipped default "
             "(with it); mean error in the set's unit, the fallback's firing, how many fits reproduce the "
             "stored fit of the method kept (within 1e-9 relative), the worst case ÷ the default before, and "
             "time ÷ the default before (the stored seconds).", "",
             "| set | cases | default before | laplacian | default now | now ÷ before | fired | reproduced | "
             "worst case ÷ before | residual, max of kept / min of fired (%) | code, max of kept / min of fired | "
             "time ÷ before |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    pair_lines: list[str] = []
    for name in (*IN_FAMILY, *CROSS_FAMILY):
        old = stored(name)
        new = {row_key(r)[1:]: r for r in rows if r["set"] == name and ERROR[name] in r}
        keys = [k for k in new if (k, "default") in old]
        if not keys:
            continue
        error = ERROR[name]
        before = np.array([old[(k, "default")][error] for k in keys])
        lap = np.array([old[(k, "laplacian")][error] for k in keys])
        now = np.array([new[k][error] for k in keys])
        fired = np.array([bool(new[k].get("fallback", {}).get("used")) for k in keys])
        residual = np.array([new[k].get("fallback", {}).get("residual", np.nan) for k in keys])
        code = np.array([new[k].get("fallback", {}).get("code", np.nan) for k in keys])
        kept = np.where(fired, lap, before)
        same = int(np.sum(np.abs(now - kept) <= 1e-9 * np.abs(kept)))
        seconds = sum(new[k]["seconds"] for k in keys) / sum(old[(k, "default")]["seconds"] for k in keys)
        spread = (f"{100 * np.nanmax(residual[~fired]):.2f} / "
                  f"{100 * np.nanmin(residual[fired]):.2f}" if fired.any() else f"{100 * np.nanmax(residual):.2f} / –")
        spread_code = (f"{np.nanmax(code[~fired]):.2f} / {np.nanmin(code[fired]):.2f}" if fired.any()
                       else f"{np.nanmax(code):.2f} / –")
        lines.append(f"| {name} | {len(keys)} | {before.mean():.4g} | {lap.mean():.4g} | {now.mean():.4g} | "
                     f"{now.mean() / before.mean():.3f} | {fired.sum()}/{len(keys)} | {same}/{len(keys)} | "
                     f"{(now / before).max():.2f} | {spread} | {spread_code} | {seconds:.2f} |")
        if name in CROSS_FAMILY:
            pair_lines += pair_table(name, keys, old, new)
    return "\n".join(lines + [""] + criteria_table(rows) + [""] + clutter_table(rows) + [""] + pair_lines)


def criteria_table(rows: list[dict]) -> list[str]:
    """Each criterion alone, both (shipped) and other thresholds, from the rows' residual and code and
    the stored fits of the default and ``laplacian``: mean error per set (fired / cases)."""
    from statfit.core.methods import FALLBACK_CODE, FALLBACK_RESIDUAL

    def rule(residual: float, code: float):
        return lambda f: f["residual"] > residual or f["code"] > code

    rules = {"residual alone": rule(FALLBACK_RESIDUAL, np.inf), "code alone": rule(np.inf, FALLBACK_CODE),
             "both (shipped)": rule(FALLBACK_RESIDUAL, FALLBACK_CODE)}
    rules |= {f"residual {t:.3g}%, code {FALLBACK_CODE:g}": rule(t / 100, FALLBACK_CODE) for t in (1.0, 1.5, 3.0)}
    rules |= {f"residual {FALLBACK_RESIDUAL:.0%}, code {t:g}": rule(FALLBACK_RESIDUAL, t) for t in (3.0, 4.0, 5.0)}
    names = (*IN_FAMILY, *CROSS_FAMILY)
    lines = [f"Each criterion alone (residual > {FALLBACK_RESIDUAL:.0%}, code > {FALLBACK_CODE:g}), both, and other "
             "thresholds: mean error per set (fired / cases).", "", "| rule | " + " | ".join(names) + " |",
             "|---|" + "---|" * len(names)]
    for label, fires in rules.items():
        cells = []
        for name in names:
            old = stored(name)
            new = {row_key(r)[1:]: r for r in rows if r["set"] == name and ERROR[name] in r and "fallback" in r}
            keys = [k for k in new if (k, "default") in old]
            fired = [fires(new[k]["fallback"]) for k in keys]
            value = np.mean([old[(k, "laplacian" if f else "default")][ERROR[name]] for k, f in zip(keys, fired)])
            cells.append(f"{value:.4g} ({sum(fired)}/{len(keys)})")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def clutter_table(rows: list[dict]) -> list[str]:
    """§8: the face error (mm) before and now, without and with clutter, and the fallback's firing."""
    old = clutter_stored()
    new = {r["seed"]: r for r in rows if r["set"] == "§8"}
    seeds = [s for s in new if s in old]
    if not seeds:
        return []
    lines = ["§8 (ICT people with clutter; face error, mm, mean over the vertices within 3 cm of an inner "
             "landmark): the stored default and the shipped one.", "",
             "| clutter per shape point | scans | face mm before | face mm now | fired | residual max (%) | "
             "code max | worst scan ÷ before |", "|---|---|---|---|---|---|---|---|"]
    for clutter in CLUTTER:
        before = np.array([old[s][f"face_mm_{clutter}"] for s in seeds])
        now = np.array([new[s][f"face_mm_{clutter}"] for s in seeds])
        reports = [new[s].get(f"fallback_{clutter}", {}) for s in seeds]
        fired = sum(bool(r.get("used")) for r in reports)
        residual = max(r.get("residual", float("nan")) for r in reports)
        code = max(r.get("code", float("nan")) for r in reports)
        lines.append(f"| {clutter} | {len(seeds)} | {before.mean():.3f} | {now.mean():.3f} | {fired}/{len(seeds)} | "
                     f"{100 * residual:.2f} | {code:.2f} | {(now / before).max():.3f} |")
    return lines


def pair_table(name: str, keys: list[tuple], old: dict, new: dict) -> list[str]:
    """Per (people, model) pair: every stored single method, the default before and now."""
    methods = ("pca", "statistical", "hybrid", "laplacian", "mean")
    lines = [f"{name} per pair (mm, mean held-out distance; best: the lowest stored single method).", "",
             "| people | model | cases | mean | default before | laplacian | best single | default now | fired | "
             "now ÷ best | now ÷ mean |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    pairs = dict.fromkeys(k[:2] for k in keys)
    for pair in [*pairs, ("all", "all")]:
        cases = [k for k in keys if pair == ("all", "all") or k[:2] == pair]

        def mean(method: str) -> float:
            values = [old[(k, method)]["held"] for k in cases if (k, method) in old]
            return float(np.mean(values)) if len(values) == len(cases) else float("nan")

        singles = {m: mean(m) for m in ("default", *methods[:-1]) if np.isfinite(mean(m))}
        best = min(singles, key=singles.get)
        now = float(np.mean([new[k]["held"] for k in cases]))
        fired = sum(bool(new[k].get("fallback", {}).get("used")) for k in cases)
        lines.append(f"| {pair[0]} | {pair[1]} | {len(cases)} | {mean('mean'):.2f} | {mean('default'):.2f} | "
                     f"{mean('laplacian'):.2f} | {singles[best]:.2f} ({best}) | {now:.2f} | {fired}/{len(cases)} | "
                     f"{now / singles[best]:.2f} | {now / mean('mean'):.2f} |")
    return lines + [""]


def main() -> None:
    study_main(__doc__, run_case, runs, ROWS, report, row_key)


if __name__ == "__main__":
    main()
