"""What the benchmark parts share: the machine's description, timing, child processes, data paths
and the section format that ``run.py`` assembles into docs/benchmarks.md."""
from __future__ import annotations

import json
import platform
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any, Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
# The one definition of where the shared data lie (tests and studies import it from here).
ICT = ROOT.parent / "shared" / "data" / "ict-face"
ICT_MODEL = ICT / "ict_face_identity.npz"
ICT_EXPRESSIONS = ICT / "ict_face_expressions.npz"
MAKEHUMAN = ROOT.parent / "shared" / "data" / "makehuman"
FIXTURES = ROOT / "tests"  # generated test data (texture_fixtures.py) that benchmarks reuse
PACKAGES = ("torch", "numpy", "scipy", "trimesh", "libigl", "cholespy", "largesteps", "pycpd")


@dataclass
class Section:
    """One part of the report: a markdown body (tables, prose), the PNG figures it shows and the
    raw numbers (saved as JSON next to the report)."""

    name: str
    title: str
    markdown: str
    figures: list[Path] = field(default_factory=list)
    data: dict[str, Any] = field(default_factory=dict)


def machine(device: str = "cpu") -> dict[str, Any]:
    """CPU (and GPU) model, core count, Python and library versions, date."""
    import torch

    cpuinfo = Path("/proc/cpuinfo")
    cpu = next((line.split(":", 1)[1].strip() for line in cpuinfo.read_text().splitlines()
                if line.startswith("model name")), platform.processor()) if cpuinfo.exists() else platform.processor()
    info: dict[str, Any] = {"cpu": cpu, "cores": torch.get_num_threads(), "python": platform.python_version(),
                            "date": time.strftime("%Y-%m-%d")}
    if device == "cuda" and torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name()
        info["cuda"] = torch.version.cuda
    for package in PACKAGES:
        try:
            info[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            info[package] = "not installed"
    return info


def median_ms(fn: Callable[[], Any], repeats: int, sync: Callable[[], None] = lambda: None) -> float:
    """Median wall time of ``fn()`` in milliseconds over ``repeats`` calls, after one warm-up call."""
    fn()
    sync()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times))


def grid(side: int) -> tuple[np.ndarray, np.ndarray]:
    """A side × side triangulated grid: vertices (side², 3) in the unit square, faces (2(side−1)², 3)."""
    i, j = np.meshgrid(np.arange(side), np.arange(side), indexing="ij")
    vertices = np.stack([i.ravel(), j.ravel(), np.zeros(side * side)], axis=1) / side
    idx = (i * side + j)[:-1, :-1].ravel()
    faces = np.concatenate([np.stack([idx, idx + side, idx + 1], 1),
                            np.stack([idx + 1, idx + side, idx + side + 1], 1)])
    return vertices, faces


def peak_rss_mb() -> float:
    """This process's peak resident set (MB) since it started or last exec'd (``VmHWM``; unlike
    ``ru_maxrss``, not inherited from a large parent across fork)."""
    status = Path("/proc/self/status")
    if status.exists():
        for line in status.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def in_child(module: str, function: str, *args: Any, threads: int = 2) -> Any:
    """``module.function(*args)`` run in a fresh Python process (its own peak memory, no state shared
    with other measurements); arguments and result go through JSON. The child's peak RSS (MB) is
    added to a dict result as ``peak_rss_mb``."""
    code = (f"import json, sys, torch; torch.set_num_threads({threads}); "
            f"sys.path.insert(0, {str(ROOT / 'benchmarks')!r}); import common, {module}; "
            f"result = {module}.{function}(*json.loads(sys.argv[1])); "
            "result = result | {'peak_rss_mb': common.peak_rss_mb()} if isinstance(result, dict) else result; "
            "print('\\n' + json.dumps(result))")
    done = subprocess.run([sys.executable, "-c", code, json.dumps(list(args))], capture_output=True, text=True,
                          cwd=ROOT)
    if done.returncode != 0:
        raise RuntimeError(f"{module}.{function}{args} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def markdown_table(header: list[str], rows: list[list[Any]]) -> str:
    """A markdown table; floats are printed with 3 significant digits."""
    def cell(value: Any) -> str:
        return f"{value:.3g}" if isinstance(value, float) else str(value)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def save_figure(fig: Any, path: Path, dpi: int = 100) -> None:
    """Write a matplotlib figure as PNG (creating the folder) and close it."""
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


def save_json(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1))


def timed_statfit(*argv: str) -> tuple[float, str]:
    """Wall seconds and stdout of ``statfit argv`` run in a fresh process (a failure raises, with its stderr)."""
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "statfit_cli.main", *argv], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"statfit {' '.join(argv)} failed:\n{done.stderr[-2000:]}")
    return time.perf_counter() - started, done.stdout


def alternate(names: list[str], prepare: Callable[[str], Any], variants: tuple, rounds: int,
              fit: Callable[[Any, Any], dict], line: Callable[[Any, dict], str],
              warm_up: bool = False) -> dict[tuple[str, Any], list[dict]]:
    """Two or more variants of a fit timed side by side in one process (a ratio of medians that
    drifts with the machine cancels): for each name, its input ``prepare(name)``, then ``rounds``
    rounds of ``fit(input, variant)`` for every variant in turn (after one unrecorded fit of the last
    variant with ``warm_up``), each row printed as ``name`` and ``line(variant, row)``. Rows by
    (name, variant)."""
    rows: dict[tuple[str, Any], list[dict]] = {}
    for name in names:
        prepared = prepare(name)
        if warm_up:
            fit(prepared, variants[-1])
        for _ in range(rounds):
            for variant in variants:
                row = fit(prepared, variant)
                rows.setdefault((name, variant), []).append(row)
                print(f"{name} {line(variant, row)}", flush=True)
    return rows


def median_ratio(rows: dict[tuple[str, Any], list[dict]], name: str, key: str, variant: Any, baseline: Any) -> float:
    """The median of ``key`` over ``name``'s rows of ``variant`` ÷ that of ``baseline`` (:func:`alternate`)."""
    return (statistics.median(row[key] for row in rows[(name, variant)])
            / statistics.median(row[key] for row in rows[(name, baseline)]))
