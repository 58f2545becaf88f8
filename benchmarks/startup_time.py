"""What a `statfit` process pays besides its fit, this tree against a git revision's, side by side.

    python benchmarks/startup_time.py [--against REV] [--rounds 3]

Each row is a fresh process, as a user's command is: `statfit --help`, `statfit register` of a scan
that does not exist (refused: exit 2), and `statfit register` of the
ICT jaw-open scan (4,300 points, the default method, one thread) whose wall time is split into the
fit (the summary's ``seconds``: pose search, stages, fallback test) and the rest (the interpreter,
imports, the model's load, reading the scan, writing the mesh). The revision runs from a git
worktree of it (its library and its CLI), the two alternating ``--rounds`` times, so a drift of the
machine's load falls on both. Prints every row, then the medians and their ratio.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
CLI = "import sys; from statfit_cli.main import main; main(sys.argv[1:])"


def tree_path(revision: str | None, folder: Path) -> Path:
    """A folder whose ``statfit`` and ``statfit_cli`` are this tree's (``revision`` None) or a
    worktree of ``revision``'s (made in ``folder``), for PYTHONPATH."""
    source = ROOT
    if revision:
        source = folder / "worktree"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(source), revision],
                       check=True, capture_output=True)
    shim = folder / ("old" if revision else "new")
    shim.mkdir()
    (shim / "statfit").symlink_to(source / "statfit")
    (shim / "statfit_cli").symlink_to(source / "cli")
    return shim


def timed(path: Path, argv: list[str], code: int = 0) -> tuple[float, str]:
    """Wall seconds of ``statfit argv`` in a fresh process importing from ``path``, and its stdout;
    the process must exit with ``code``."""
    env = dict(os.environ, PYTHONPATH=str(path))
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", CLI, *argv], env=env, capture_output=True, text=True,
                          cwd=path)    # not a folder holding another tree's statfit, which `-c` would import first
    wall = time.perf_counter() - started
    if done.returncode != code:
        raise SystemExit(f"statfit {' '.join(argv)} failed: {done.stderr.strip()[-500:]}")
    return wall, done.stdout


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--against", help="a git revision to compare with")
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    from cases import ICT_MODEL, scan_case
    from statfit.io.mesh import points_bytes

    with tempfile.TemporaryDirectory() as temporary:
        folder = Path(temporary)
        scan = folder / "scan.ply"
        scan.write_bytes(points_bytes(scan_case("jaw-open").points))
        trees = {"this tree": tree_path(None, folder)}
        if args.against:
            trees[args.against] = tree_path(args.against, folder)
        rows: dict[str, list[dict]] = {name: [] for name in trees}
        try:
            for _ in range(args.rounds):
                for name, path in trees.items():
                    help_wall, _ = timed(path, ["--help"])
                    refusal, _ = timed(path, ["register", str(folder / "missing.ply")], code=2)
                    wall, out = timed(path, ["register", str(scan), "--model", str(ICT_MODEL), "--threads", "1",
                                             "--out", str(folder / "fit.ply"), "--json", "-q"])
                    fit = json.loads(out.strip().splitlines()[-1])["seconds"]
                    rows[name].append({"help": help_wall, "refusal": refusal, "register": wall, "fit": fit,
                                       "rest": wall - fit})
                    print(f"{name:>12}: --help {help_wall:5.2f} s; missing scan {refusal:5.2f} s; register "
                          f"{wall:5.2f} s = fit {fit:5.2f} + the rest {wall - fit:5.2f}", flush=True)
        finally:
            if args.against:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(folder / "worktree")],
                               capture_output=True)
        for key in ("help", "refusal", "register", "fit", "rest"):
            medians = {name: statistics.median(row[key] for row in rows[name]) for name in trees}
            ratio = (f"; this tree ÷ {args.against} {medians['this tree'] / medians[args.against]:.3f}"
                     if args.against else "")
            print(f"median {key}: " + ", ".join(f"{name} {value:.2f} s" for name, value in medians.items()) + ratio)


if __name__ == "__main__":
    main()
