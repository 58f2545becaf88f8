"""Big scans: ``statfit register`` (the default pipeline, automatic alignment) on ICT point clouds of
4,300, 100,000 and 1,000,000 points (``statfit synth scan --points``, seed 3: the same head, the
same view), each in a fresh process under ``/usr/bin/time -v``: wall seconds, peak resident memory
and the all-vertex error against the ground truth (``statfit eval``'s "all" mean, cm: ICT's units). A cloud
denser than the fit needs is fitted through a subsample spread over it, sized from the model
(:meth:`statfit.structures.scan.Scan.thinned`); the reference row fits every point of the
100,000-point cloud (the thinning switched off), the honest bar for the subsample's accuracy.

    python benchmarks/big_scans.py [--quick] [--all-points N,...]

``--quick``: 4,300 and 50,000 points and no reference fit (checks that the part runs; about a
minute). ``--all-points``: the point counts whose reference fit (every point) to run (default
100000; 1000000 takes ~10 minutes and ~6 GB).
"""
from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import ICT_MODEL, ROOT, Section, in_child, machine, markdown_table, save_json  # noqa: E402

FULL = {"points": (4_300, 100_000, 1_000_000), "all_points": (100_000,)}
QUICK = {"points": (4_300, 50_000), "all_points": ()}
SEED = 3
ICT_VERTICES = 11_248


def statfit_command(*argv: str) -> list[str]:
    return [sys.executable, "-m", "statfit_cli.main", *argv]


def synth(folder: Path, points: int) -> tuple[Path, Path]:
    """The scan of ``points`` points and its ground truth (the same head for every count)."""
    scan, truth = folder / f"scan_{points}.ply", folder / "gt.ply"
    subprocess.run(statfit_command("synth", "scan", "--model", str(ICT_MODEL), "--points", str(points), "--seed",
                                   str(SEED), "--out", str(scan), "--gt", str(truth)), check=True, capture_output=True)
    return scan, truth


def error_cm(fit: Path, truth: Path) -> float:
    """The all-vertex mean error of ``statfit eval`` (cm: the ICT model's units)."""
    import json

    done = subprocess.run(statfit_command("eval", str(fit), str(truth), "--json"), check=True, capture_output=True,
                          text=True)
    return float(json.loads(done.stdout)["all"]["mean"])


def timed_register(scan: Path, out: Path) -> dict:
    """Wall seconds and peak RSS (MB) of ``statfit register scan`` in a fresh process, from
    ``/usr/bin/time -v`` where it exists (else the wall time alone)."""
    command = statfit_command("register", str(scan), "--model", str(ICT_MODEL), "--out", str(out))
    timer = ["/usr/bin/time", "-v"] if Path("/usr/bin/time").exists() else []
    started = time.perf_counter()
    done = subprocess.run([*timer, *command], capture_output=True, text=True)
    seconds = time.perf_counter() - started
    if done.returncode != 0:
        raise RuntimeError(f"statfit register {scan} failed:\n{done.stderr[-2000:]}")
    peak = re.search(r"Maximum resident set size \(kbytes\): (\d+)", done.stderr)
    return {"seconds": seconds, "peak_mb": int(peak.group(1)) / 1024 if peak else None}


def fit_every_point(scan: str, out: str) -> dict:
    """The default fit of every point of ``scan`` (no subsample), in this process (called in a child)."""
    import statfit.structures.scan as scans
    from statfit.io.mesh import load_scan, mesh_bytes
    from statfit.model.statmodel import load_model
    from statfit.registration.job import register

    scans.THIN_ABOVE = float("inf")
    scans.MESH_SAMPLES = (scans.MESH_SAMPLES[0], 10**12)
    started = time.perf_counter()
    model = load_model(str(ICT_MODEL))
    result = register(model, load_scan(scan))
    Path(out).write_bytes(mesh_bytes(result.vertices, model.faces, "ply"))
    return {"seconds": time.perf_counter() - started}


def thinned(points: int) -> bool:
    """Whether ``register`` fits an ICT cloud of ``points`` points through a subsample."""
    from statfit.structures.scan import MESH_SAMPLES, THIN_ABOVE, sample_size

    return points > max(THIN_ABOVE * sample_size(ICT_VERTICES), MESH_SAMPLES[1])


def measure(quick: bool, all_points: tuple[int, ...] | None = None) -> dict:
    config = QUICK if quick else FULL
    all_points = config["all_points"] if all_points is None else all_points
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        for points in config["points"]:
            scan, truth = synth(folder, points)
            fit = folder / f"fit_{points}.ply"
            rows.append({"points": points, "fit": "subsample" if thinned(points) else "as is"}
                        | timed_register(scan, fit) | {"error_cm": error_cm(fit, truth)})
        for points in all_points:
            scan, truth = synth(folder, points)
            fit = folder / f"fit_all_{points}.ply"
            row = in_child("big_scans", "fit_every_point", str(scan), str(fit), threads=2)
            rows.append({"points": points, "fit": "every point (reference)", "seconds": row["seconds"],
                         "peak_mb": row["peak_rss_mb"], "error_cm": error_cm(fit, truth)})
    return {"rows": rows}


def run(quick: bool, device: str = "cpu", image_dir: Path | None = None) -> Section:
    data = measure(quick)
    return section(data)


def section(data: dict) -> Section:
    rows = data["rows"]
    small = next(r for r in rows if r["points"] == 4_300)
    table = markdown_table(
        ["points", "fitted", "wall s", "× 4,300", "peak MB", "error cm (all vertices)"],
        [[f"{r['points']:,}", r["fit"], r["seconds"], r["seconds"] / small["seconds"],
          "" if r["peak_mb"] is None else round(r["peak_mb"]), r["error_cm"]] for r in rows])
    text = ("`statfit register <scan> --model ict_face_identity.npz` (default pipeline, automatic alignment), one "
            "fresh process per row (`/usr/bin/time -v`; the reference row: the same fit of every point, in a "
            "child process, wall seconds without the interpreter's start). Scans: `statfit synth scan --points N "
            f"--seed {SEED}` (the same head and view).\n\n{table}")
    return Section("big_scans", "Big scans: time, memory and accuracy against the scan's size", text, data=data)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="4,300 and 50,000 points, no reference fit")
    parser.add_argument("--all-points", default=None, help="point counts to fit through every point too")
    args = parser.parse_args()
    counts = None if args.all_points is None else tuple(int(n) for n in args.all_points.split(",") if n)
    data = measure(args.quick, counts)
    save_json(ROOT / "benchmarks" / "results" / f"big_scans{'_quick' if args.quick else ''}_cpu.json",
              {"machine": machine(), **data})
    print(section(data).markdown)


if __name__ == "__main__":
    main()
