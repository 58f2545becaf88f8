"""Part 9: full bodies — building the MakeHuman body model, its file size, and `statfit render` on
a body-sized normal map (issue 14's targets: build ≤ 2 min, npz ≤ 60 MB, render ≤ 2 min at 768²).

Each step runs as the CLI command a user types, in a fresh process on a quiet machine (wall
seconds include Python's start and the model's load). The accuracy of every method on held-out
bodies is the study's (studies/study_body.py, docs/studies.md §13).

Then the same render, shortened to LOAD_ITERATIONS, on 2 threads and on the count statfit chooses,
quiet and with a second process keeping one core busy (the body is the one job here large enough
for several threads, so the one where a busy core can stall them), side by side in one run.
"""
from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

from common import MAKEHUMAN, Section, markdown_table, timed_statfit as timed
from register_speed import BUSY

FULL = {"k": 300, "samples": 5000, "size": 768}
QUICK = {"k": 40, "samples": 400, "size": 256}
LOAD_ITERATIONS, QUICK_LOAD_ITERATIONS = 100, 20


def measure(quick: bool) -> dict:
    config = QUICK if quick else FULL
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder)
        model, person, exr, cam, fit = (str(path / n) for n in ("body.npz", "p.ply", "b.exr", "c.json", "f.ply"))
        build_s, out = timed("model", "build-makehuman", str(MAKEHUMAN), "-o", model, "--k", str(config["k"]),
                             "--samples", str(config["samples"]), "--seed", "0", "--json")
        explained = json.loads(out)["variance_explained"]
        body_s, _ = timed("synth", "body", str(MAKEHUMAN), "--seed", "4", "-o", person, "-q")
        timed("synth", "normals", "--model", model, "--shape", person, "--yaw", "30", "--size", str(config["size"]),
              "--out", exr, "--camera-out", cam)
        render_s, out = timed("render", exr, "--camera", cam, "--model", model, "--out", fit, "--json", "-q")
        summary = json.loads(out)
        load = [render_under_load(exr, cam, model, fit, busy, threads, QUICK_LOAD_ITERATIONS if quick else
                                  LOAD_ITERATIONS) for busy in (False, True) for threads in ("2", None)]
        return {**config, "build_seconds": build_s, "body_seconds": body_s, "npz_mb": (path / "body.npz").stat().st_size / 1e6,
                "variance_explained": explained, "render_wall_seconds": render_s,
                "render_fit_seconds": summary["seconds"], "render_threads": summary["threads"],
                "render_stage_seconds": summary["stage_seconds"], "load": load}


def render_under_load(exr: str, cam: str, model: str, fit: str, busy: bool, threads: str | None,
                      iterations: int) -> dict:
    """One shortened render (``threads`` None: statfit's choice), quiet or beside a spinning process."""
    spinner = subprocess.Popen([sys.executable, "-c", BUSY]) if busy else None
    try:
        wall, out = timed("render", exr, "--camera", cam, "--model", model, "--out", fit, "--iterations",
                          str(iterations), "--json", "-q", *(("--threads", threads) if threads else ()))
    finally:
        if spinner is not None:
            spinner.kill()
            spinner.wait()
    summary = json.loads(out)
    return {"busy": busy, "asked": threads, "threads": summary["threads"], "wall_seconds": wall,
            "fit_seconds": summary["seconds"], "iterations": summary["iterations"]}


def run(quick: bool, device: str, image_dir) -> Section:
    data = measure(quick)
    rows = [["model build-makehuman", f"k {data['k']}, {data['samples']} bodies", data["build_seconds"], "≤ 120 s"],
            ["model file", "float32 shapedirs", f"{data['npz_mb']:.1f} MB", "≤ 60 MB"],
            ["synth body", "one body (reads MakeHuman's 1,258 targets)", data["body_seconds"], ""],
            ["render (default)", f"{data['size']}² body map, wall", data["render_wall_seconds"], "≤ 120 s"],
            ["render (default)", "of which the fit", data["render_fit_seconds"], ""]]
    text = (markdown_table(["step", "size", "seconds (or size)", "target"], rows)
            + "\n\nVariance explained by the first k modes: "
            + ", ".join(f"{k}: {v:.4%}" for k, v in data["variance_explained"].items())
            + ".\n\nThe fit's stages (s): "
            + ", ".join(f"{k} {v:.1f}" for k, v in data["render_stage_seconds"].items())
            + f" (on {data['render_threads']} thread{'s' if data['render_threads'] != 1 else ''}).")
    if "load" in data:
        quiet = {r["asked"]: r["fit_seconds"] for r in data["load"] if not r["busy"]}
        text += (f"\n\nThe same render shortened to {data['load'][0]['iterations']} iterations, quiet and with a "
                 "second process spinning on one core, side by side in one run (fit seconds):\n\n" + markdown_table(
                     ["threads", "one core busy", "fit s", "× quiet"],
                     [["chosen (%d)" % r["threads"] if r["asked"] is None else r["asked"], "yes" if r["busy"] else "no",
                       r["fit_seconds"], r["fit_seconds"] / quiet[r["asked"]]] for r in data["load"]]))
    return Section("bodies", "Full bodies: building the MakeHuman model, rendering a body", text, data=data)
