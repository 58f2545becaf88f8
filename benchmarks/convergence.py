"""Part 2: convergence (the paper's Fig. 4 analogue). Error against the ground truth over all /
observed / unobserved vertices, vs iteration and vs wall time, for every method at its tuned
(converged) settings and for the default pipeline, on an ICT partial scan and an ICT normal map
(targets with an expression outside the identity model).

The fit reports its vertices every 10 iterations (``on_snapshot``); the time spent scoring them is
subtracted from the wall-time axis. Each fit runs in a fresh process.
"""
from __future__ import annotations

import time
from pathlib import Path

from common import Section, in_child, markdown_table, save_figure

from statfit.core.methods import METHODS as REGISTRY  # noqa: E402

METHODS = ("default", *(name for name, method in REGISTRY.items() if "register" in method.tuned))
FULL = {"scan": ("jaw-open", "smile"), "normals": ("jaw-open",), "size": 256, "iterations": None, "methods": METHODS}
QUICK = {"scan": ("jaw-open",), "normals": ("jaw-open",), "size": 96, "iterations": 60,
         "methods": ("default", "statistical", "laplacian", "pca")}
REACH = 1.25  # "time to reach": first snapshot within this factor of the case's best final error


def trace(job: str, case_name: str, method: str, size: int, iterations: int | None, device: str) -> dict:
    """One fit's error trace: lists of iteration, seconds and errors {all, observed, unobserved}."""
    from cases import ict_model, normal_case, relative_errors, scan_case

    model = ict_model()
    points: list[dict] = []
    scoring = 0.0
    case = scan_case(case_name) if job == "scan" else normal_case(case_name, size)

    def on_snapshot(iteration: int, vertices) -> None:
        nonlocal scoring
        begin = time.perf_counter()
        points.append({"iteration": iteration, "seconds": begin - start - scoring,
                       **relative_errors(vertices, case.target, case.observed)})
        scoring += time.perf_counter() - begin

    overrides = {"iterations": iterations} if iterations else {}
    start = time.perf_counter()
    if job == "scan":
        from statfit.registration.job import register

        register(model, case.points, method, device=device, on_snapshot=on_snapshot, **overrides)
    else:
        from statfit.render.job import reconstruct

        reconstruct(model, case.normal_map, case.camera, method, device=device, on_snapshot=on_snapshot, **overrides)
    return {"job": job, "case": case_name, "method": method, "trace": points}


def measure(quick: bool, device: str = "cpu") -> dict:
    """Traces of every method on every case of the mode."""
    config = QUICK if quick else FULL
    traces = [in_child("convergence", "trace", job, name, method, config["size"], config["iterations"], device)
              for job in ("scan", "normals") for name in config[job] for method in config["methods"]]
    return {"device": device, "config": config, "traces": traces}


def section(results: dict, image_dir: Path) -> Section:
    """Final errors, time to reach REACH × the best final error, and the convergence plots."""
    rows, figures = [], []
    cases = sorted({(t["job"], t["case"]) for t in results["traces"]})
    for job, name in cases:
        traces = [t for t in results["traces"] if (t["job"], t["case"]) == (job, name)]
        best = min(t["trace"][-1]["all"] for t in traces)
        for t in traces:
            last = t["trace"][-1]
            reached = next((p for p in t["trace"] if p["all"] <= REACH * best), None)
            rows.append([f"{job} {name}", t["method"], last["iteration"] + 1, last["seconds"], last["all"],
                         last["observed"], last["unobserved"],
                         f"{reached['seconds']:.3g} s (it {reached['iteration']})" if reached else "never",
                         f"{t['peak_rss_mb']:.0f}"])
        figure = image_dir / f"convergence_{job}_{name}_{results['device']}.png"
        _plot(traces, f"{job}: {name}", figure)
        figures.append(figure)
    config = results["config"]
    body = "\n\n".join([
        f"Cases: ICT partial scans {', '.join(config['scan'])}; ICT normal maps {', '.join(config['normals'])} at "
        f"{config['size']}². Every method at its tuned settings (`--preset tuned`), the default pipeline as "
        "shipped" + (f"; all cut to {config['iterations']} iterations (quick mode)" if config["iterations"] else "")
        + ". Errors: mean vertex distance to the ground truth / its RMS radius. Time to reach: the first "
        f"snapshot whose error over all vertices is within {REACH}× the case's best final error.",
        markdown_table(["case", "method", "iterations", "fit s", "final all", "observed", "unobserved",
                        "time to reach", "peak RSS MB"], rows),
        *[f"![convergence]({f.relative_to(image_dir.parent).as_posix()})" for f in figures],
    ])
    return Section("convergence", "Convergence", body, figures, results)


def _plot(traces: list[dict], title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(13, 7.5), sharey="col")
    for column, subset in enumerate(("all", "observed", "unobserved")):
        for t in traces:
            its = [p["iteration"] + 1 for p in t["trace"]]
            secs = [max(p["seconds"], 1e-3) for p in t["trace"]]
            errs = [p[subset] for p in t["trace"]]
            axes[0, column].plot(its, errs, label=t["method"])
            axes[1, column].plot(secs, errs, label=t["method"])
        axes[0, column].set_title(f"{subset} vertices")
        axes[0, column].set_xlabel("iteration")
        axes[1, column].set_xlabel("wall time (s)")
        for row in (0, 1):
            axes[row, column].set_xscale("log")
            axes[row, column].set_yscale("log")
            axes[row, column].grid(True, which="both", alpha=0.3)
    axes[0, 0].set_ylabel("mean error / RMS radius")
    axes[1, 0].set_ylabel("mean error / RMS radius")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(title)
    save_figure(fig, path)


def run(quick: bool, device: str, image_dir: Path) -> Section:
    """Measure and format this part."""
    return section(measure(quick, device), image_dir)
