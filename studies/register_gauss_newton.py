"""Study behind the closed-form ``pca`` stage and the ``fast`` pipeline (docs/studies.md §9).

Every pipeline below fits the ICT identity model to the registration study's nine partial scans
(six test cases, three held out; benchmarks/cases.py), one thread, one process; the all-vertex
error (cm) and the fit's seconds go to studies/results/register_gauss_newton.json, and the table
is printed as markdown. Results are cached per pipeline: delete the JSON to re-measure.

    python studies/register_gauss_newton.py              # about 10 minutes on one core
    python studies/register_gauss_newton.py --k 50       # off-span: fit the first 50 of 100 modes
    python studies/register_gauss_newton.py --report     # the tables from the saved results

With ``--k K`` the fits use the model truncated to its first K modes while the targets still come
from all 100 identity modes plus the expression: a person the fitted model cannot represent even
without the expression (the protocol of issue 11's "a real person is never in the model's span").
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from cases import FORMER_DEFAULT, HELD_OUT_SCAN_CASES, STUDY_SCAN_CASES, ict_model, scan_case  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "register_gauss_newton.json"
STEP_0006 = "GN → hybrid β 1 lr 0.006 200 it (default until 2026-11-25)"   # before its step became 0.03 (§12)


def pipelines() -> dict:
    from statfit.core.methods import PIPELINES
    from statfit.core.settings import Settings

    def gn(noise: float, levels: int = 5) -> Settings:
        return Settings("pca", 200, 0.0, optimizer="gauss-newton", noise=noise, levels=levels)

    def stat(iterations: int, lr: float, beta: float, gain: float) -> Settings:
        return Settings("statistical", iterations, lr, beta=beta, mode_gain=gain)

    from cases import former_default_stages

    return {
        "default (shipped)": PIPELINES["register"]["default"].stages,
        FORMER_DEFAULT: former_default_stages(),
        "GN σ 0, no continuation": (gn(0.0, 1),),
        "GN σ 0.01, no continuation": (gn(0.01, 1),),
        "GN σ 0.03, no continuation": (gn(0.03, 1),),
        "GN σ 0.01 → stat γ 0.5 lr 0.01 300 it": (gn(0.01, 1), stat(300, 0.01, 1000.0, 0.5)),
        "GN σ 0.03 → stat γ 1 lr 0.03 500 it": (gn(0.03, 1), stat(500, 0.03, 1000.0, 1.0)),
        "GN σ 0.3 … 0.003, 5 levels (pca)": (gn(0.003),),
        "GN σ 1 … 0.01, 5 levels": (gn(0.01),),
        "GN 5 levels → stat γ 0.5 lr 0.01 300 it": (gn(0.003), stat(300, 0.01, 1000.0, 0.5)),
        "GN 5 levels → stat γ 1 lr 0.01 300 it": (gn(0.003), stat(300, 0.01, 1000.0, 1.0)),
        "GN 5 levels → stat β 30 γ 1 lr 0.01 300 it": (gn(0.003), stat(300, 0.01, 30.0, 1.0)),
        "GN 5 levels → stat β 300 γ 1 lr 0.03 500 it": (gn(0.003), stat(500, 0.03, 300.0, 1.0)),
        "GN 5 levels → laplacian λ 19 lr 0.003 300 it": (gn(0.003), Settings("laplacian", 300, 0.003, lam=19.0)),
        "GN 5 levels → laplacian λ 19 lr 0.003 600 it": (gn(0.003), Settings("laplacian", 600, 0.003, lam=19.0)),
        "GN 5 levels → hybrid β 30 lr 0.003 300 it": (gn(0.003), Settings("hybrid", 300, 0.003, beta=30.0, lam=19.0)),
        "GN 5 levels → hybrid β 1 lr 0.003 600 it": (gn(0.003), Settings("hybrid", 600, 0.003, beta=1.0, lam=19.0)),
        STEP_0006: (
            PIPELINES["register"]["default"].stages[0], Settings("hybrid", 200, 0.006, beta=1.0, lam=19.0)),
        "GN 5 levels → hybrid β 1 lr 0.006 300 it": (gn(0.003), Settings("hybrid", 300, 0.006, beta=1.0, lam=19.0)),
        "stat γ 1 lr 0.1 600 it (from the mean)": (stat(600, 0.1, 1000.0, 1.0),),
    }


OFF_SPAN = ("default (shipped)", STEP_0006, FORMER_DEFAULT, "GN σ 0.01, no continuation",
            "GN σ 0.3 … 0.003, 5 levels (pca)", "GN 5 levels → stat γ 0.5 lr 0.01 300 it")


def measure(stages, k: int | None = None) -> dict:
    import numpy as np
    import torch

    from statfit.registration.job import register

    torch.set_num_threads(1)
    errors, seconds = {}, {}
    for name in STUDY_SCAN_CASES:
        case = scan_case(name)
        model = ict_model() if k is None else ict_model().truncated(k)
        result = register(model, case.points, stages=stages, threads=1)
        errors[name] = float(np.linalg.norm(result.vertices - case.target, axis=1).mean())
        seconds[name] = result.seconds
    return {"errors": errors, "seconds": seconds}


def report(results: dict) -> str:
    cases = list(STUDY_SCAN_CASES)
    test = [c for c in cases if c not in HELD_OUT_SCAN_CASES]
    mean = lambda row, names: sum(row["errors"][c] for c in names) / len(names)  # noqa: E731
    lines = ["| pipeline | " + " | ".join(cases) + " | mean test | mean held out | s per fit |",
             "|---" * (len(cases) + 4) + "|"]
    for name, row in results.items():
        cells = " | ".join(f"{row['errors'][c]:.3f}" for c in cases)
        per_fit = sum(row["seconds"].values()) / len(row["seconds"])
        lines.append(f"| {name} | {cells} | {mean(row, test):.4f} | {mean(row, HELD_OUT_SCAN_CASES):.4f} | "
                     f"{per_fit:.2f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--report", action="store_true", help="only print the tables of saved results")
    parser.add_argument("--k", type=int, default=None, help="fit a model truncated to K modes (off-span)")
    args = parser.parse_args()
    saved = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {}
    protocols = {"full model (100 modes)": (None, list(pipelines()))} if args.k is None else {}
    protocols |= {f"first {args.k} modes": (args.k, list(OFF_SPAN))} if args.k else {}
    if not args.report:
        for protocol, (k, names) in protocols.items():
            results = saved.setdefault(protocol, {})
            for name in names:
                if name not in results:
                    print(f"{protocol}: {name}…", file=sys.stderr, flush=True)
                    results[name] = measure(pipelines()[name], k)
                    RESULTS.parent.mkdir(parents=True, exist_ok=True)
                    RESULTS.write_text(json.dumps(saved, indent=1))
    for protocol, results in saved.items():
        print(f"\n{protocol}:\n\n{report(results)}")


if __name__ == "__main__":
    main()
