"""Part 4: the two jobs end to end, as a user runs them: `statfit register` (ICT, 4,300-point scan)
and `statfit render` (ICT, one 512² normal map), per method, each a fresh `statfit` process timed
from launch to exit, with its peak memory (the process's maximum resident set) and its error
against the ground truth.

Every method runs at the paper's settings (500 iterations for register, 3000 for render); the
default pipelines run as shipped (their own iteration counts).
"""
from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

from cases import normal_case, relative_errors, scan_case
from common import ICT_MODEL, Section, markdown_table

from statfit.core.methods import METHODS as REGISTRY  # noqa: E402

METHODS = tuple(name for name, method in REGISTRY.items() if "register" in method.tuned)
FULL = {"register_iterations": None, "render_iterations": None, "size": 512, "methods": ("default", *METHODS)}
QUICK = {"register_iterations": 50, "render_iterations": 30, "size": 128, "methods": ("default", "statistical", "laplacian")}


# Runs the CLI in this interpreter and reports its peak RSS (VmHWM) on stderr's last line at exit.
LAUNCHER = ("import atexit, sys; sys.path.insert(0, {folder!r}); import common; "
            "atexit.register(lambda: sys.stderr.write(f'\\npeak_rss_mb {{common.peak_rss_mb()}}\\n')); "
            "from statfit_cli.main import main; main(sys.argv[1:])")


def _measure(argv: list[str]) -> tuple[float, float]:
    """Wall seconds and peak RSS (MB) of one ``statfit`` process."""
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", LAUNCHER.format(folder=str(Path(__file__).resolve().parent)),
                           *argv], capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"statfit {' '.join(argv)} failed: {done.stderr[-2000:]}")
    return seconds, float(done.stderr.strip().splitlines()[-1].split()[1])


def measure(quick: bool, device: str = "cpu") -> dict:
    """Run every method of both jobs; returns rows of {job, method, iterations, seconds, peak_rss_mb, errors}."""
    from statfit.io.mesh import points_bytes, read_mesh
    from statfit.io.files import write_atomic
    from statfit.io.normalmap import write_normal_map

    config = QUICK if quick else FULL
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        scan = scan_case("jaw-open")
        write_atomic(folder / "scan.ply", points_bytes(scan.points))
        normals = normal_case("jaw-open", config["size"])
        write_normal_map(folder / "normals.exr", normals.normal_map.normals, normals.normal_map.mask, normals.camera)
        jobs = {"register": (["register", str(folder / "scan.ply")], scan, config["register_iterations"]),
                "render": (["render", str(folder / "normals.exr")], normals, config["render_iterations"])}
        for job, (argv, case, iterations) in jobs.items():
            for method in config["methods"]:
                preset = "tuned" if method == "default" else "paper"
                out = folder / f"{job}-{method}.ply"
                extra = ["--iterations", str(iterations)] if iterations else []
                seconds, peak = _measure([*argv, "--model", str(ICT_MODEL), "--method", method, "--preset", preset,
                                          "--device", device, "--out", str(out), "-q", *extra])
                vertices, _ = read_mesh(out)
                rows.append({"job": job, "method": method, "preset": preset, "iterations": iterations,
                             "seconds": seconds, "peak_rss_mb": peak,
                             "errors": relative_errors(vertices, case.target, case.observed)})
    return {"device": device, "config": config, "rows": rows}


def section(results: dict) -> Section:
    """The table of ``measure``'s results."""
    config = results["config"]
    rows = [[r["job"], r["method"], r["preset"], r["iterations"] or "method's own", r["seconds"], r["peak_rss_mb"],
             r["errors"]["all"], r["errors"]["observed"], r["errors"]["unobserved"]] for r in results["rows"]]
    body = "\n\n".join([
        f"ICT head, jaw-open cases: register a 4,300-point scan; render a {config['size']}² normal map. "
        "Wall time of the whole `statfit` process (import, model load, alignment, fit, writing the mesh); "
        "peak RSS of that process. Errors: mean vertex distance to the ground truth / its RMS radius.",
        markdown_table(["job", "method", "preset", "iterations", "wall s", "peak RSS MB", "error all",
                        "observed", "unobserved"], rows),
    ])
    return Section("end_to_end", "End-to-end timings", body, [], results)


def run(quick: bool, device: str, image_dir: Path) -> Section:
    """Measure and format this part."""
    return section(measure(quick, device))
