"""The GPU benchmark (issue 38, part 7): one command, a few minutes on one GPU.

    python benchmarks/gpu.py [--device cuda] [--quick] [--out FILE.json] [--profile FILE.txt]
                             [--only register|render]

Prints a markdown table: the filter step at 2^20 vertices (k = 100); one prefactored Laplacian solve
on ICT's mesh with cholespy and with the dense inverse; one closest-point query of the scan term
(ICT, 4,300 points) and the register default's fallback test on the same points; ``register`` (ICT
jaw-open, 4,300 points) and ``render`` (ICT jaw-open, 512²) at the default and at the paper's
settings (render's also op by op, ``STATFIT_CUDA_GRAPHS=0``; both defaults also with the cholespy
solve, which no CUDA graph captures, where the default, ``auto``, solves by the dense inverse on a
GPU; each row says whether its fit ran as a captured graph, :mod:`statfit.core.graphs`, and the
seconds of its stages) — seconds per fit; ms per iteration, from two runs of every stage cut to 50
and to 250 iterations (the difference over the iterations between), and from the whole fit's loop
stage times (host; the figure to read where the set-up varies more than 200 iterations cost, as
register's); the set-up (the 50-iteration run less its iterations: pose search, factorisations,
model to the device); torch ops and host waits per iteration of each job's loop (counted with a
dispatch mode, as ``../shared/tools/sync_count.py`` counts them); and fits per second over a run of
scans, one after another and together (``register_many``: the gradient stage of all stepped as one,
with its ops per iteration for 8 fits) and by ``statfit batch register`` at its defaults over 16
scans, with ``statfit register``'s wall seconds for one (whole commands, on the device and on the
CPU), and over ICT normal maps (paper ``statistical``'s loop without alignment, 4 maps one after
another, 16 together by ``reconstruct_many``; ops per iteration for 8; with ``--profile FILE`` the
ops of those fits stepped together by their device time, op by op). A warm-up fit runs first (CUDA's
start). With ``--device cpu`` the same numbers on one CPU thread, for the ratio measured on the same
machine; with ``--only JOB`` only that job's rows (and the filter's), for a short card run. The
shipped settings' rows come first, then the fits together, then the comparisons, so a run cut short
by a time limit keeps the former.
The ICT data must be at ../shared/data/ict-face.
"""
from __future__ import annotations

import argparse
import collections
import contextlib
import itertools
import json
import os
import sys
import time
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
import torch
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).resolve().parent))

RENDER_TOGETHER_ITERATIONS = 300    # the maps' fits timed one after another and together
BATCH_SCANS = 16                     # `statfit batch register`'s scans (32 until session 33: see main)
# A fit's stages that run once, not every iteration (the rest are its loop's).
SET_UP_STAGES = ("alignment", "gauss-newton", "fallback test")

STATFIT = [sys.executable, "-m", "statfit_cli.main"]

WAITING = ("_local_scalar_dense", "nonzero", "masked_select", "_unique", "unique_consecutive", "unique_dim",
           "repeat_interleave", "equal", "is_nonzero", "masked_scatter")


class OpCounter(TorchDispatchMode):
    """Counts every torch op dispatched inside the block, by name."""

    def __init__(self):
        super().__init__()
        self.ops: collections.Counter = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops[func.__name__] += 1
        return func(*args, **(kwargs or {}))


def per_iteration(run) -> tuple[float, float]:
    """(ops, host waits) per iteration of ``run(iterations) -> iterations run``: 120 minus 20."""
    short, long = OpCounter(), OpCounter()
    with short:
        done_short = run(20)
    with long:
        done_long = run(120)
    n = done_long - done_short
    ops = (sum(long.ops.values()) - sum(short.ops.values())) / n
    waits = sum(long.ops[k] - short.ops.get(k, 0) for k in long.ops if any(w in k for w in WAITING)) / n
    return ops, waits


def synchronize(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def median_ms(call, device: str, repeats: int = 20) -> float:
    """``call()`` after one warm-up call: the median of ``repeats`` timed calls, in ms."""
    call()
    times = []
    for _ in range(repeats):
        synchronize(device)
        start = time.perf_counter()
        call()
        synchronize(device)
        times.append(1e3 * (time.perf_counter() - start))
    return float(np.median(times))


def filter_step_ms(device: str, vertices: int, k: int = 100) -> float:
    """One statistical filter step (two mat-vecs) on (3·vertices,) float32, median ms."""
    from statfit.core.filters import StatisticalFilter

    generator = torch.Generator(device=device).manual_seed(0)
    basis_t = torch.linalg.qr(torch.randn(3 * vertices, k, device=device, generator=generator))[0].T.contiguous()
    step = StatisticalFilter(basis_t, beta=1000.0)
    gradient = torch.randn(vertices, 3, device=device, generator=generator)
    return median_ms(lambda: step(gradient), device)


def solve_ms(device: str, model, solver: str) -> float:
    """One prefactored (I + λL)⁻¹ solve of (N, 3) float32 on ``model``'s mesh (λ = 19), median ms."""
    from statfit.core.filters import LaplacianFilter

    solve = LaplacianFilter(model.template, model.faces, 19.0, solver=solver, device=device)
    rhs = torch.randn(len(model.template), 3, device=device)
    return median_ms(lambda: solve(rhs), device)


def closest_ms(device: str, model, points: np.ndarray) -> float:
    """One closest-point query (the scan term's, k = 2) of ``points`` on ``model``'s mean, median ms."""
    from statfit.geometry.closest import ClosestPointQuery

    query = ClosestPointQuery(model.faces, model.num_vertices, k=2, device=device)
    vertices = torch.as_tensor(model.template, dtype=torch.float32, device=device)
    targets = torch.as_tensor(points, dtype=torch.float32, device=device)
    host = targets.double().cpu().numpy()
    return median_ms(lambda: query(vertices, targets, host), device)


def fallback_test_ms(model, points: np.ndarray) -> float:
    """The register default's fallback test on ``model``'s mean (on the host, wherever the fit ran):
    the exact distance of ``points`` to the surface and the shape's code, median ms."""
    from statfit.geometry.metrics import inside_distance
    from statfit.model.params import project

    def test() -> None:
        inside_distance(points, model.template, model.faces)
        project(model, model.template)

    return median_ms(test, "cpu")


@contextlib.contextmanager
def cuda_graphs(on: bool) -> Iterator[None]:
    """Fits in the block captured in CUDA graphs (the default) or run op by op (``STATFIT_CUDA_GRAPHS``)."""
    os.environ["STATFIT_CUDA_GRAPHS"] = "1" if on else "0"
    try:
        yield
    finally:
        os.environ.pop("STATFIT_CUDA_GRAPHS", None)


def profile_together(fit: Callable[[], object], device: str, out: Path, title: str) -> None:
    """Torch's profiler over ``fit()`` run op by op (a replayed graph hides its kernels), after one
    warm-up run: the ops by their own device time (CPU time on a CPU), under ``title``, written to ``out``."""
    from torch.profiler import ProfilerActivity, profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device == "cuda" else [])
    with cuda_graphs(False):
        timed(fit, device)                              # warm-up: the kernels' first launches
        with profile(activities=activities) as profiler:
            timed(fit, device)
    key = "self_device_time_total" if device == "cuda" else "self_cpu_time_total"
    out.write_text(f"{title}, op by op, on {device}\n" + profiler.key_averages().table(sort_by=key, row_limit=40))


def captured(outcomes) -> str:
    """How many of a fit of many's outcomes ran a stage as a captured CUDA graph, as "k of n"."""
    fits = [each.fit for each in outcomes if each.fit is not None]
    return f"{sum('graph' in fit.stage_seconds for fit in fits)} of {len(outcomes)}"


def timed(fit, device: str):
    """One run of ``fit()``: (result, seconds)."""
    synchronize(device)
    start = time.perf_counter()
    result = fit()
    synchronize(device)
    return result, time.perf_counter() - start


def save(rows: dict[str, object], out: Path | None) -> None:
    """The rows so far as JSON in ``out`` (if given): written after every section, so a run stopped
    by its time limit still leaves what it measured."""
    if out:
        out.write_text(json.dumps(rows, indent=1))


def report(rows: dict[str, object], out: Path | None) -> None:
    """The rows as a markdown table on stdout, and as JSON in ``out``."""
    width = max(len(key) for key in rows)
    print(f"| {'measure':<{width}} | value |\n|{'-' * (width + 2)}|---|")
    for key, value in rows.items():
        shown = f"{value:.3g}" if isinstance(value, float) else "-" if value is None else str(value)
        print(f"| {key:<{width}} | {shown} |", flush=True)
    save(rows, out)


def ict_scans(ict, count: int, first_seed: int) -> list[np.ndarray]:
    """``count`` scans (4,300 points, a view within 40° of the front) of ICT people, seeds from ``first_seed``."""
    from statfit.synth.sample import sample_target, scan_from_view

    scans = []
    for seed in range(first_seed, first_seed + count):
        person_rng = np.random.default_rng(seed)
        person = sample_target(ict, person_rng)
        scans.append(scan_from_view(person, ict.faces, person_rng, 4300, float(person_rng.uniform(-40, 40))))
    return scans


def register_together(ict, embedded, points, device: str, rows: dict, count: int) -> None:
    """Rows of fits per second over ``count`` ICT scans, one after another and stepped together
    (``register_many``), and ops and waits per iteration of 8 fits together."""
    import statfit
    from statfit.registration.many import register_many
    scans = ict_scans(ict, count, 100)
    synchronize(device)
    start = time.perf_counter()
    for points_of_one in scans:
        statfit.register(ict, points_of_one, "default", device=device)
    synchronize(device)
    rows[f"register default, {count} scans one after another: fits/s"] = count / (time.perf_counter() - start)
    start = time.perf_counter()
    outcomes = register_many(ict, scans, "default", device=device)
    synchronize(device)
    rows[f"register default, {count} scans together (register_many): fits/s"] = count / (time.perf_counter() - start)
    rows[f"register default, {count} scans together: captured"] = captured(outcomes)
    rows["register together, 8 fits: ops/it"], rows["register together, 8 fits: waits/it"] = per_iteration(
        lambda it: register_many(embedded, [points] * 8, "statistical", preset="paper", align="none", device=device,
                                 iterations=it)[0].fit.iterations)


def register_cli(ict, model_path: Path, device: str, rows: dict, count: int, rounds: int = 2) -> None:
    """Rows of the whole commands (processes, imports, CUDA's start) on ``device`` and on the CPU,
    the same machine: ``statfit register`` of one ICT scan, ``rounds`` fresh processes each, the
    devices alternating (median wall seconds: the measure ``--device auto`` goes by); and fits per
    second of ``statfit batch register`` over ``count`` ICT scans (PLY files) at its defaults
    (``--workers`` the cores, ``--together`` from the card's memory)."""
    import subprocess
    import tempfile

    import trimesh
    with tempfile.TemporaryDirectory() as folder:
        scans = Path(folder) / "scans"
        scans.mkdir()
        for index, points in enumerate(ict_scans(ict, count, 500)):
            trimesh.PointCloud(points).export(scans / f"scan{index:03d}.ply")
        devices = list(dict.fromkeys((device, "cpu")))
        walls: dict[str, list[float]] = {on: [] for on in devices}
        for _, on in itertools.product(range(rounds), devices):
            start = time.perf_counter()
            done = subprocess.run([*STATFIT, "register", str(scans / "scan000.ply"), "--model", str(model_path),
                                   "--out", str(Path(folder) / "one.ply"), "--device", on, "-q"],
                                  capture_output=True, text=True)
            walls[on].append(time.perf_counter() - start if done.returncode == 0 else float("nan"))
        for on in devices:
            rows[f"statfit register, one ICT scan, --device {on}: wall s (median of {rounds})"] = float(
                np.median(walls[on]))
        for on in devices:
            start = time.perf_counter()
            done = subprocess.run([*STATFIT, "batch", "register", str(scans / "*.ply"), "--model", str(model_path),
                                   "--out-dir", str(Path(folder) / f"fits-{on}"), "--device", on, "-q"],
                                  capture_output=True, text=True)
            seconds = time.perf_counter() - start
            fitted = len(list((Path(folder) / f"fits-{on}").glob("*.ply")))
            rows[f"statfit batch register, {count} ICT scans, --device {on}, defaults: fits/s"] = (
                fitted / seconds if done.returncode == 0 else f"exit {done.returncode}: {done.stderr.strip()[-200:]}")


def render_together(ict, embedded, normal_map, camera, device: str, rows: dict, args: argparse.Namespace) -> None:
    """Rows of fits per second over ICT normal maps, one after another and stepped together
    (``reconstruct_many``), their profile (``--profile``), and ops and waits per iteration of 8."""
    import statfit
    from statfit.render.many import reconstruct_many
    from statfit.renderer.images import render_target
    from statfit.structures.normal_map import NormalMap
    from statfit.synth.sample import camera_for_view, sample_target
    # Many maps: the steady loop's throughput (paper statistical, RENDER_TOGETHER_ITERATIONS, no alignment).
    size, alone_count, together_count = (128, 2, 4) if args.quick else (512, 4, 16)
    maps, cameras = [], []
    for seed in range(together_count):
        person = sample_target(ict, np.random.default_rng(300 + seed))
        cameras.append(camera_for_view(person, 15.0 * (seed % 5 - 2), 0.0, size))
        maps.append(NormalMap(*render_target(person, ict.faces, cameras[-1])))
    steady = dict(preset="paper", align="none", iterations=RENDER_TOGETHER_ITERATIONS, device=device)
    synchronize(device)
    start = time.perf_counter()
    for one_map, one_camera in zip(maps[:alone_count], cameras[:alone_count]):
        statfit.reconstruct(ict, one_map, one_camera, "statistical", **steady)
    synchronize(device)
    label = f"render paper statistical, {RENDER_TOGETHER_ITERATIONS} iterations at {size}², no alignment"
    rows[f"{label}, one after another: fits/s"] = alone_count / (time.perf_counter() - start)
    start = time.perf_counter()
    outcomes = reconstruct_many(ict, maps, cameras, "statistical", **steady)
    synchronize(device)
    rows[f"{label}, {together_count} together (reconstruct_many): fits/s"] = together_count / (time.perf_counter() - start)
    rows[f"{label}, {together_count} together: captured"] = captured(outcomes)
    if args.profile:
        profiled = 20
        profile_together(lambda: reconstruct_many(ict, maps, cameras, "statistical", **{**steady, "iterations": profiled}),
                         device, args.profile, f"{together_count} maps together at {size}², {profiled} iterations")
    rows["render together, 8 fits: ops/it"], rows["render together, 8 fits: waits/it"] = per_iteration(
        lambda it: reconstruct_many(embedded, [normal_map] * 8, [camera] * 8, "statistical",
                                    preset="paper", align="none", device=device, iterations=it)[0].fit.iterations)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--quick", action="store_true", help="small sizes: checks that it runs")
    parser.add_argument("--out", type=Path, help="also write the numbers as JSON here")
    parser.add_argument("--profile", type=Path, help="also profile the maps' fits stepped together, op by op, "
                        "and write the ops by their device time here")
    parser.add_argument("--only", choices=("register", "render"), help="one job's rows (and the filter's): a "
                        "shorter card run")
    args = parser.parse_args()
    wanted = {"register", "render"} if args.only is None else {args.only}
    device = args.device
    if device == "cpu":
        torch.set_num_threads(1)
    from cases import normal_case, scan_case
    from common import ICT_MODEL
    import statfit
    from statfit.model.statmodel import default_model_path, load_model
    from statfit.synth.sample import camera_for_view, sample_target, scan_from_view
    from statfit.structures.normal_map import NormalMap
    from statfit.renderer.images import render_target
    from statfit.core.fit import StageTimer

    rows: dict[str, object] = {"device": torch.cuda.get_device_name() if device == "cuda" else "cpu (1 thread)",
                               "torch": torch.__version__}
    rows["filter step 2^20 (ms)"] = filter_step_ms(device, 1 << (14 if args.quick else 20))
    ict = load_model(ICT_MODEL)
    for solver in ("cholespy", "dense"):
        rows[f"Laplacian solve, ICT's 11,248 vertices, {solver} (ms)"] = solve_ms(device, ict, solver)
    save(rows, args.out)

    embedded = load_model(default_model_path())
    rng = np.random.default_rng(3)
    target = sample_target(embedded, rng)
    points = scan_from_view(target, embedded.faces, rng, 4300, 20.0)
    camera = camera_for_view(target, 20.0, 0.0, 256)
    normal_map = NormalMap(*render_target(target, embedded.faces, camera))
    if "register" in wanted:
        rows["register ops/it"], rows["register waits/it"] = per_iteration(
            lambda it: statfit.register(embedded, points, "statistical", preset="paper", align="none", device=device,
                                        iterations=it).iterations)
    if "render" in wanted:
        rows["render ops/it"], rows["render waits/it"] = per_iteration(
            lambda it: statfit.reconstruct(embedded, normal_map, camera, "statistical", preset="paper", align="none",
                                           device=device, iterations=it).iterations)
    save(rows, args.out)

    scan = scan_case("jaw-open")
    if "register" in wanted:
        rows["closest points, ICT, 4,300 scan points, k = 2 (ms)"] = closest_ms(device, ict, scan.points)
        rows["register's fallback test, ICT, 4,300 scan points (ms)"] = fallback_test_ms(ict, scan.points)
    normals = normal_case("jaw-open", 128 if args.quick else 512)
    def register_with(method: str, preset: str, iterations: int | None, **overrides):
        extra = {} if iterations is None else {"iterations": iterations}
        return lambda timer: statfit.register(ict, scan.points, method, preset=preset, device=device, timer=timer,
                                              **extra, **overrides)

    def render_with(method: str, preset: str, iterations: int | None, **overrides):
        extra = {} if iterations is None else {"iterations": iterations}
        return lambda timer: statfit.reconstruct(ict, normals.normal_map, normals.camera, method, preset=preset,
                                                 device=device, timer=timer, **extra, **overrides)

    few, more = (10, 30) if args.quick else (50, 250)
    # name: (job, method, preset, CUDA graphs on, whole fit timed, settings overridden)
    # The shipped settings first, then the fits together, the comparisons last (a run stopped by its
    # time limit keeps the former).
    shipped = {"register default": (register_with, "default", "tuned", True, True, {}),
               "register paper statistical": (register_with, "statistical", "paper", True, True, {}),
               "render paper statistical": (render_with, "statistical", "paper", True, True, {}),
               "render default": (render_with, "default", "tuned", True, True, {})}
    comparisons = {"register default, cholespy": (register_with, "default", "tuned", True, True, {"solver": "cholespy"}),
                   "render paper statistical, op by op": (render_with, "statistical", "paper", False, False, {}),
                   "render default, cholespy, op by op": (render_with, "default", "tuned", True, True,
                                                          {"solver": "cholespy"})}
    jobs = shipped | comparisons

    def time_job(name: str) -> None:
        make, method, preset, graphs_on, whole, overrides = jobs[name]
        timer = StageTimer()
        fit = make(method, preset, None, **overrides)
        with cuda_graphs(graphs_on):
            result, seconds = timed(lambda: fit(timer), device) if whole and not args.quick else (None, float("nan"))
            short, short_seconds = timed(lambda: make(method, preset, few, **overrides)(None), device)
            long, long_seconds = timed(lambda: make(method, preset, more, **overrides)(None), device)
        per_iteration_s = (long_seconds - short_seconds) / max(long.iterations - short.iterations, 1)
        rows[f"{name}: s per fit"] = seconds
        rows[f"{name}: iterations"] = None if result is None else result.iterations
        rows[f"{name}: ms/it"] = 1e3 * per_iteration_s
        # The loop's stage times over the whole fit's iterations: where the set-up's spread between the
        # two short fits exceeds their iterations' difference (register's), the difference says nothing.
        loop_s = sum(spent for stage, spent in timer.seconds.items() if stage not in SET_UP_STAGES)
        rows[f"{name}: loop ms/it (its stage times)"] = 1e3 * loop_s / result.iterations if result else float("nan")
        rows[f"{name}: set-up s"] = short_seconds - short.iterations * per_iteration_s
        rows[f"{name}: CUDA graph"] = "; ".join(sorted(set(timer.notes.values()))) or "-"
        rows[f"{name}: stage s"] = ", ".join(f"{stage} {value:.2f}" for stage, value in timer.seconds.items())
        print(f"{name}: {seconds:.2f} s, {1e3 * per_iteration_s:.2f} ms/it, graph {rows[f'{name}: CUDA graph']}",
              file=sys.stderr, flush=True)
        save(rows, args.out)

    timed(lambda: register_with("pca", "tuned", None)(None), device)      # warm-up: CUDA's start, the caches
    for name in shipped:
        if name.split()[0] in wanted:
            time_job(name)
    # The fits together before the whole commands: session 33's 200 s on an H200 ended inside the
    # commands' rows (fresh processes; a batch then of 32 scans at ~0.3 fits a second), so the render
    # rows never ran.
    if "register" in wanted:
        register_together(ict, embedded, points, device, rows, 4 if args.quick else 8)
        save(rows, args.out)
    if "render" in wanted:
        render_together(ict, embedded, normal_map, camera, device, rows, args)
        save(rows, args.out)
    if "register" in wanted:
        register_cli(ict, ICT_MODEL, device, rows, 4 if args.quick else BATCH_SCANS)
        save(rows, args.out)
    for name in comparisons:
        if name.split()[0] in wanted:
            time_job(name)
    report(rows, args.out)


if __name__ == "__main__":
    main()
