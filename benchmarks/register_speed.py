"""Part 6: registration speed and accuracy side by side — the shipped default, the default until
2026-11-25 (two statistical stages, 4,000 + 1,333 steps) and the closed-form ``pca`` on the ICT
head (4,300-point scans).

1. Seconds of one fit (jaw-open case, timed inside a fresh process after a warm-up fit) on 1
   thread, 2 threads and the thread count statfit chooses, on a quiet machine and with a second
   process keeping one core busy. The study's scans lie in the model's frame, so these fits run
   with ``align="none"``; one more row per method times the same call with the automatic alignment
   (``register``'s default, which checks the pose even of a scan already in place; §8 times it on
   scans in any pose).
2. All-vertex error (cm) of each method on the registration study's nine cases (six test cases,
   three held out), one fit per case on the chosen thread count: the accuracy the speed buys.
"""
from __future__ import annotations

import subprocess
import sys
import time

from cases import FORMER_DEFAULT, HELD_OUT_SCAN_CASES, STUDY_SCAN_CASES, register_named, scan_case
from common import Section, in_child, markdown_table

METHODS = ("default", FORMER_DEFAULT, "pca")
THREADS = (1, 2, None)  # None: statfit's choice
FULL = {"cases": tuple(STUDY_SCAN_CASES), "iterations": None, "methods": METHODS}
QUICK = {"cases": ("jaw-open",), "iterations": 40, "methods": ("default", "pca")}   # the former default: 27 s a fit
BUSY = "import time\nend = time.time() + 3600\nwhile time.time() < end: pass"


def fit_once(method: str, threads: int | None, iterations: int | None, case: str = "jaw-open",
             align: str = "none") -> dict:
    """Fit seconds (after a warm-up fit) and the error (cm), in this process (called in a child)."""
    import numpy as np

    from cases import ict_model
    from statfit.core.threads import choose_threads, flush_denormals_everywhere

    flush_denormals_everywhere()
    data = scan_case(case)
    model = ict_model()
    register_named(model, data.points, method, iterations=5, threads=threads, align=align)
    started = time.perf_counter()
    result = register_named(model, data.points, method, iterations=iterations, threads=threads, align=align)
    seconds = time.perf_counter() - started
    return {"seconds": seconds, "iterations": result.iterations,
            "threads": choose_threads(model.basis.size, threads),
            "error": float(np.linalg.norm(result.vertices - data.target, axis=1).mean())}


def measure(quick: bool) -> dict:
    config = QUICK if quick else FULL
    timings = []
    for load in ("quiet", "busy"):
        busy = subprocess.Popen([sys.executable, "-c", BUSY]) if load == "busy" else None
        try:
            for method in config["methods"]:
                for threads in THREADS:
                    row = in_child("register_speed", "fit_once", method, threads, config["iterations"], threads=2)
                    timings.append({"load": load, "method": method, "asked": threads, "align": "none"} | row)
                if load == "quiet":
                    row = in_child("register_speed", "fit_once", method, None, config["iterations"], "jaw-open",
                                   "auto", threads=2)
                    timings.append({"load": load, "method": method, "asked": None, "align": "auto"} | row)
        finally:
            if busy is not None:
                busy.kill()
    errors = {method: {case: in_child("register_speed", "fit_once", method, None, config["iterations"], case,
                                      threads=1)["error"] for case in config["cases"]} for method in config["methods"]}
    return {"timings": timings, "errors": errors}


def run(quick: bool, device: str, image_dir) -> Section:
    data = measure(quick)
    rows = []
    for method in data["errors"]:
        for threads in THREADS:
            cells = {r["load"]: r for r in data["timings"]
                     if r["method"] == method and r["asked"] == threads and r["align"] == "none"}
            quiet, busy = cells["quiet"], cells["busy"]
            rows.append([method, "chosen (%d)" % quiet["threads"] if threads is None else threads, "none",
                         quiet["iterations"], quiet["seconds"], busy["seconds"], busy["seconds"] / quiet["seconds"]])
        for auto in (r for r in data["timings"] if r["method"] == method and r["align"] == "auto"):
            rows.append([method, "chosen (%d)" % auto["threads"], "auto", auto["iterations"], auto["seconds"], "", ""])
    speed = markdown_table(["method", "threads", "alignment", "iterations", "quiet s", "one core busy s",
                            "busy / quiet"], rows)
    cases = list(next(iter(data["errors"].values())))
    test = [c for c in cases if c not in HELD_OUT_SCAN_CASES]
    held = [c for c in cases if c in HELD_OUT_SCAN_CASES]
    mean = lambda values: sum(values) / len(values) if values else float("nan")  # noqa: E731
    accuracy = markdown_table(
        ["method", *cases, "mean test", "mean held out"],
        [[m, *(e[c] for c in cases), mean([e[c] for c in test]), mean([e[c] for c in held])]
         for m, e in data["errors"].items()])
    text = (f"Fit seconds inside a warm process (jaw-open, ICT, 4,300 points); 'one core busy': a second process "
            f"spins on one core meanwhile.\n\n{speed}\n\nAll-vertex error (cm, ICT's units) per study case, each fit "
            f"on the chosen thread count:\n\n{accuracy}")
    return Section("register_speed", "Registration: speed per thread count and load, with accuracy", text, data=data)
