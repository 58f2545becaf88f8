"""Speed of `statfit register` on the ICT model: 4,300-point partial scan, per method.

Each method runs in a fresh process (so peak memory is its own): import and model-load times are
reported apart from the fit, a 20-iteration warm-up fit absorbs the process's first-call costs,
and the timed fit is broken down per stage of the loop. Prints a
markdown table; `--json PATH` also saves the numbers.

    python studies/bench_register.py [--iterations 500] [--threads 2] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from common import ICT, machine  # noqa: E402

METHODS = ("statistical", "hybrid", "laplacian", "pca", "regularized", "none", "default")
STAGES = ("correspondences", "loss", "backward", "filter", "step")


def measure(method: str, iterations: int | None, threads: int, preset: str) -> dict:
    """Run one fit in this process and return its timings (called in a child process)."""
    import resource
    import time

    started = time.perf_counter()
    import numpy as np
    import torch

    from statfit.model.statmodel import load_model
    from statfit.registration.job import register
    from statfit.synth.sample import load_delta, sample_target, scan_from_view

    torch.set_num_threads(threads)
    imported = time.perf_counter()
    model = load_model(ICT / "ict_face_identity.npz")
    loaded = time.perf_counter()
    rng = np.random.default_rng(3)
    target = sample_target(model, rng, delta=load_delta(str(ICT / "ict_face_expressions.npz"), "jawOpen"))
    points = scan_from_view(target, model.faces, rng, 4300, 30.0)
    warm_start = time.perf_counter()
    register(model, points, method, preset=preset, iterations=20)  # first-call costs: BLAS threads, allocator
    warm_up = time.perf_counter() - warm_start
    result = register(model, points, method, preset=preset, iterations=iterations)
    total_iterations = sum(s.iterations for s in result.stages)
    return {"method": method, "preset": preset, "iterations": total_iterations,
            "import_s": imported - started, "load_s": loaded - imported, "warm_up_s": warm_up,
            "fit_s": result.seconds,
            "per_iteration_ms": {k: 1e3 * result.stage_seconds.get(k, 0.0) / total_iterations for k in STAGES},
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=None, help="default: each method's own")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--preset", default="paper", help="paper (500 iterations each) or tuned")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(measure(args.child, args.iterations, args.threads, args.preset)))
        return
    rows = []
    for method in METHODS:
        preset = "tuned" if method == "default" else args.preset
        command = [sys.executable, __file__, "--child", method, "--threads", str(args.threads), "--preset", preset]
        if args.iterations:
            command += ["--iterations", str(args.iterations)]
        out = subprocess.run(command, check=True, capture_output=True, text=True).stdout
        rows.append(json.loads(out.strip().splitlines()[-1]))
    info = machine()
    print(f"{info['cpu']}, {args.threads} threads; python {info['python']}, torch {info['torch']}, "
          f"numpy {info['numpy']}, scipy {info['scipy']}\n")
    print("| method | iterations | fit s | " + " | ".join(f"{s} ms/it" for s in STAGES)
          + " | import s | load s | 20-it warm-up s | peak RSS MB |")
    print("|---" * (len(STAGES) + 7) + "|")
    for r in rows:
        stages = " | ".join(f"{r['per_iteration_ms'][s]:.2f}" for s in STAGES)
        print(f"| {r['method']} | {r['iterations']} | {r['fit_s']:.2f} | {stages} | {r['import_s']:.2f} | "
              f"{r['load_s']:.2f} | {r['warm_up_s']:.2f} | {r['peak_rss_mb']:.0f} |")
    if args.json:
        args.json.write_text(json.dumps({"machine": info, "threads": args.threads, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
