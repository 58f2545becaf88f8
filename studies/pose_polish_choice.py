"""Which refined pose the automatic pose search keeps: the refinement's best, or the one that
polishes best (issue 37, part 1; docs/studies.md §33).

The search (statfit.registration.pose.search) refines its three best distinct poses with the first
modes and a free scale, then polishes one with every mode at the units' scale. A fuzz of the CLI
found a face cut of the embedded head refused on a scan of that head: the refinement's free scale
stretched the mask over the head's side, where it scored better than where it belongs; polished,
the true pose scores far better. Variants of the choice (``POLISHED_SWITCH``):

- ``refined``: the refinement's best always (the search before this study; switch = ∞);
- ``shipped``: the refinement's best unless another candidate polishes 1.25× better;
- ``polished``: the candidate that polishes best always (switch = 1).

Every candidate is polished in every variant, so a case's fits differ only where the variants keep
different candidates; those cases alone are refitted (the others' rows are the shipped fit's).
Cases: §17's protocol (studies/cross_family.py: half scans without landmarks, people of one family
fitted with another family's model, held-out half's mean distance, mm), seeds 0 and 1 (§17's stored
people, on which 1.25 was chosen) and 2 and 3 (people no study had fitted: the check).

    python studies/pose_polish_choice.py              # 108 cases, ~15 min on 2 cores
    python studies/pose_polish_choice.py --report
"""
from __future__ import annotations

import math
import sys
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "pose_polish_choice.json"
SWITCH = {"refined": math.inf, "shipped": 1.25, "polished": 1.0}
CHOSEN_ON, CHECKED_ON = (0, 1), (2, 3)


def _fit(key: tuple, switch: float) -> tuple[dict, list, list]:
    """The default's fit of the §17 case ``key`` with ``switch``; its row (held or error) and the
    candidates' refined and lead-polished scores."""
    from unittest import mock

    import torch

    from cross_family import fit_case
    from statfit.registration.pose import search

    torch.set_num_threads(1)
    refined, polished = [], []
    refine, polish = search.refine_with_first_modes, search.polish_pose

    def refine_logged(*args, **kwargs):
        out = refine(*args, **kwargs)
        refined.append(out[1])
        return out

    def polish_logged(*args, **kwargs):
        out = polish(*args, **kwargs)
        polished.append(out[1])
        return out

    with mock.patch.object(search, "refine_with_first_modes", refine_logged), \
            mock.patch.object(search, "polish_pose", polish_logged), \
            mock.patch.object(search, "POLISHED_SWITCH", switch):
        try:
            row = fit_case(*key, "default")
            result = {"held": row["held"]}
        except Exception as error:  # noqa: BLE001 - a refusal is this case's result
            result = {"error": f"{type(error).__name__}: {error}"[:160]}
    return result, refined, polished[:len(refined)]


def _kept(refined: list, polished: list, switch: float) -> int:
    best = min(range(len(refined)), key=refined.__getitem__)
    other = min(range(len(polished)), key=polished.__getitem__)
    return other if polished[best] > switch * polished[other] else best


def run_case(people: str, model: str, seed: int, half: str) -> dict:
    import warnings

    warnings.simplefilter("ignore")
    key = (people, model, seed, half)
    shipped, refined, polished = _fit(key, SWITCH["shipped"])
    row = {"people": people, "model": model, "seed": seed, "half": half, "refined_scores": refined,
           "polished_scores": polished}
    if not refined:        # refused before the refinement: every variant alike
        return row | {variant: shipped for variant in SWITCH} | {f"{v}_kept": None for v in SWITCH}
    kept = {variant: _kept(refined, polished, switch) for variant, switch in SWITCH.items()}
    for variant, switch in SWITCH.items():
        row[f"{variant}_kept"] = kept[variant]
        row[variant] = shipped if kept[variant] == kept["shipped"] else _fit(key, switch)[0]
    return row


def runs() -> list[tuple]:
    import default_fallback

    stored = sorted({tuple(run[1:]) for run in default_fallback.runs() if run[0] == "§17"})
    return [(people, model, seed, half) for people, model, first, half in stored if first == 0
            for seed in (*CHOSEN_ON, *CHECKED_ON)]


def row_key(row: dict) -> tuple:
    return (row["people"], row["model"], row["seed"], row["half"])


def report(rows: list[dict]) -> str:
    lines = ["§17's half scans without landmarks: the default under each choice of the refined pose; held-out mm "
             "over the cases every variant fitted; refused: the pose search's refusals; changed: the cases whose "
             "kept candidate differs from `refined`'s, and among them those lower / higher by over 2%.", "",
             "| people | cases | variant | held-out mean | refused | changed | lower | higher |",
             "|---|---|---|---|---|---|---|---|"]
    for label, seeds in (("§17's (chosen on)", CHOSEN_ON), ("new (checked on)", CHECKED_ON)):
        chosen = [row for row in rows if row["seed"] in seeds]
        fitted = [row for row in chosen if all("held" in row[v] for v in SWITCH)]
        for variant in SWITCH:
            held = [row[variant]["held"] for row in fitted]
            changed = [row for row in chosen if row[f"{variant}_kept"] != row["refined_kept"]]
            lower = sum(1 for row in changed if "held" in row[variant] and "held" in row["refined"]
                        and row[variant]["held"] < 0.98 * row["refined"]["held"])
            higher = sum(1 for row in changed if "held" in row[variant] and "held" in row["refined"]
                         and row[variant]["held"] > 1.02 * row["refined"]["held"])
            refused = sum(1 for row in chosen if "error" in row[variant])
            lines.append(f"| {label} | {len(chosen)} ({len(fitted)} fitted by all) | {variant} | "
                         f"{sum(held) / max(len(held), 1):.3f} | {refused} | {len(changed)} | {lower} | {higher} |")
    lines += ["", "The changed cases (held-out mm or refused, per variant; the candidates' refined and polished "
              "scores):", "",
              "| people | model | seed | half | refined | shipped | polished | refined scores | polished scores |",
              "|---|---|---|---|---|---|---|---|---|"]
    show = lambda result: f"{result['held']:.2f}" if "held" in result else "refused"  # noqa: E731
    by = defaultdict(list)
    for row in rows:
        if len({row[f"{v}_kept"] for v in SWITCH}) > 1:
            by[row["seed"] in CHECKED_ON].append(row)
    for row in by[False] + by[True]:
        lines.append(f"| {row['people']} | {row['model']} | {row['seed']} | {row['half']} | "
                     + " | ".join(show(row[v]) for v in SWITCH) + " | "
                     + ", ".join(f"{s:.3f}" for s in row["refined_scores"]) + " | "
                     + ", ".join(f"{s:.3f}" for s in row["polished_scores"]) + " |")
    return "\n".join(lines)


def main() -> None:
    study_main(__doc__, run_case, runs, RESULTS, report, row_key)


if __name__ == "__main__":
    main()
