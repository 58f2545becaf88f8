"""A scan as a text point cloud against the same points as a binary PLY: reading them, and the whole
`statfit register`, side by side in one run.

    python benchmarks/point_text_time.py [--points 1000000] [--rounds 2]

The embedded head's `synth scan --points N --seed 3` is written as PLY and as `.xyz` (both the
PLY's float32 points). Reading: `statfit.io.mesh.read_points` of each, alternating, in this process
on one thread (best of ``--rounds``); the text reader is NumPy's `loadtxt` (statfit/io/point_text.py),
trimesh's own XYZ reader alongside for comparison. Then `statfit register` of each in a fresh
process with `--threads 1`, alternating ``--rounds`` times: wall seconds and peak memory
(`/usr/bin/time -v` where it exists). Checks that both files read to the same points.
"""
from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

from common import machine  # noqa: E402


def best_seconds(read, rounds: int) -> float:
    times = []
    for _ in range(rounds):
        started = time.perf_counter()
        read()
        times.append(time.perf_counter() - started)
    return min(times)


def register_row(scan: Path, folder: Path) -> tuple[float, float | None]:
    """Wall seconds and peak MB of `statfit register scan --threads 1` in a fresh process."""
    command = [sys.executable, "-m", "statfit_cli.main", "register", str(scan), "--out", str(folder / "fit.ply"),
               "--threads", "1", "-q"]
    timer = "/usr/bin/time" if Path("/usr/bin/time").exists() else None
    started = time.perf_counter()
    done = subprocess.run(([timer, "-v"] if timer else []) + command, capture_output=True, text=True)
    seconds = time.perf_counter() - started
    if done.returncode != 0:
        raise RuntimeError(f"register {scan} failed:\n{done.stderr[-2000:]}")
    peak = re.search(r"Maximum resident set size \(kbytes\): (\d+)", done.stderr)
    return seconds, int(peak.group(1)) / 1024 if peak else None


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args(argv)
    import torch
    import trimesh

    from statfit.io.mesh import read_points

    torch.set_num_threads(1)
    print(machine())
    with tempfile.TemporaryDirectory() as name:
        folder = Path(name)
        ply, text = folder / "scan.ply", folder / "scan.xyz"
        for path in (ply, text):
            subprocess.run([sys.executable, "-m", "statfit_cli.main", "synth", "scan", "--seed", "3", "--points",
                            str(args.points), "--out", str(path)], check=True, capture_output=True)
        assert np.array_equal(read_points(ply), read_points(text)), "the two files hold other points"
        print(f"{args.points:,} points: PLY {ply.stat().st_size / 1e6:.1f} MB, text {text.stat().st_size / 1e6:.1f} MB")
        reads = {"PLY (trimesh)": best_seconds(lambda: read_points(ply), args.rounds),
                 "text (numpy.loadtxt)": best_seconds(lambda: read_points(text), args.rounds),
                 "text (trimesh's XYZ reader)": best_seconds(lambda: trimesh.load(text, process=False), args.rounds)}
        for what, seconds in reads.items():
            print(f"read {what}: {seconds:.2f} s")
        rows: dict[str, list] = {"PLY": [], "text": []}
        for _ in range(args.rounds):
            for what, path in (("PLY", ply), ("text", text)):
                rows[what].append(register_row(path, folder))
                seconds, peak = rows[what][-1]
                print(f"register from {what}: {seconds:.2f} s, peak {peak or float('nan'):.0f} MB", flush=True)
    return {"reads": reads, "register": rows}


if __name__ == "__main__":
    main()
