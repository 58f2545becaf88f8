"""Speed of `statfit render` on the ICT model: one 512² normal map, 3000 iterations, per method.

The target is an ICT identity sample plus the jawOpen expression seen from yaw 20°. Each method runs
in a fresh process (peak memory is its own); a 20-iteration warm-up fit absorbs first-call costs; the
timed fit (rigid alignment included) is broken down per stage of the loop ("loss" is rasterize +
normals + antialias + the loss). Prints a markdown table; `--json PATH` also saves the numbers.

    python studies/bench_render_fit.py [--methods default,statistical] [--size 512] [--threads 2] [--device cpu]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_register import ICT, machine  # noqa: E402

METHODS = ("default", "statistical", "hybrid", "laplacian", "pca", "regularized", "none")
STAGES = ("alignment", "filter", "loss", "backward", "step")


def measure(method: str, size: int, iterations: int | None, threads: int, device: str) -> dict:
    """Run one fit in this process and return its timings (called in a child process)."""
    import resource
    import time

    import numpy as np
    import torch

    from statfit.structures.normal_map import NormalMap
    from statfit.render.job import reconstruct
    from statfit.model.statmodel import load_model
    from statfit.synth.sample import camera_for_view, load_delta, sample_target
    from statfit.renderer.images import render_target

    torch.set_num_threads(threads)
    model = load_model(ICT / "ict_face_identity.npz")
    target = sample_target(model, np.random.default_rng(3), 1.0,
                           load_delta(str(ICT / "ict_face_expressions.npz"), "jawOpen"), 0.8)
    camera = camera_for_view(target, 20.0, 0.0, size)
    normal_map = NormalMap(*render_target(target, model.faces, camera))
    preset = "tuned" if method == "default" else "paper"
    reconstruct(model, normal_map, camera, method, preset=preset, iterations=20, device=device)
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    started = time.perf_counter()
    result = reconstruct(model, normal_map, camera, method, preset=preset, iterations=iterations, device=device)
    wall = time.perf_counter() - started
    total = sum(s.iterations for s in result.stages)
    row = {"method": method, "preset": preset, "iterations": total, "size": size, "device": device, "wall_s": wall,
           "stage_s": {k: result.stage_seconds.get(k, 0.0) for k in STAGES},
           "per_iteration_ms": {k: 1e3 * result.stage_seconds.get(k, 0.0) / total for k in STAGES if k != "alignment"},
           "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}
    if device == "cuda":
        row["peak_gpu_mb"] = torch.cuda.max_memory_allocated() / 2**20
        row["gpu"] = torch.cuda.get_device_name()
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--iterations", type=int, default=None, help="default: each method's own (3000)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(measure(args.child, args.size, args.iterations, args.threads, args.device)))
        return
    rows = []
    for method in args.methods.split(","):
        command = [sys.executable, __file__, "--child", method, "--size", str(args.size), "--threads",
                   str(args.threads), "--device", args.device]
        if args.iterations:
            command += ["--iterations", str(args.iterations)]
        out = subprocess.run(command, check=True, capture_output=True, text=True).stdout
        rows.append(json.loads(out.strip().splitlines()[-1]))
    info = machine()
    gpu = f"; GPU {rows[0]['gpu']}" if "gpu" in rows[0] else ""
    print(f"{info['cpu']}, {args.threads} threads{gpu}; python {info['python']}, torch {info['torch']}; "
          f"{args.size}×{args.size}, device {args.device}\n")
    print("| method | iterations | wall s | alignment s | " + " | ".join(f"{s} ms/it" for s in STAGES[1:])
          + " | peak RSS MB |" + (" peak GPU MB |" if gpu else ""))
    print("|---" * (len(STAGES) + 4 + bool(gpu)) + "|")
    for r in rows:
        stages = " | ".join(f"{r['per_iteration_ms'][s]:.2f}" for s in STAGES[1:])
        print(f"| {r['method']} | {r['iterations']} | {r['wall_s']:.1f} | {r['stage_s']['alignment']:.1f} | {stages} | "
              f"{r['peak_rss_mb']:.0f} |" + (f" {r['peak_gpu_mb']:.0f} |" if gpu else ""))
    if args.json:
        args.json.write_text(json.dumps({"machine": info, "threads": args.threads, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
