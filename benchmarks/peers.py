"""Peers on the scan cases: Nicolet et al.'s own ``largesteps`` code against statfit's ``laplacian``
method on the same objective, and three other non-rigid registrations (trimesh's ``nricp_amberg``
and ``nricp_sumner``, pycpd's coherent point drift), template → partial scan.

Every fit runs in a fresh process (``common.in_child``) with the same thread count, in statfit's
unit frame (template centred, unit RMS radius). The adapters take arrays in that frame, so the
tests run them on the embedded model.

    python benchmarks/peers.py [--quick] [--device cpu|cuda] [--json PATH]
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np
import torch

from cases import SCAN_CASES, ict_model, relative_errors, scan_case
from common import Section, in_child, markdown_table, save_json
from statfit.geometry.closest import ClosestPointQuery
from statfit.core.fit import run_fit
from statfit.structures.frame import Frame
from statfit.core.methods import build
from statfit.core.settings import FitSpace, Settings
from statfit.objectives.scan import ScanObjective
from statfit.registration.job import register

THREADS = 2
# (λ, lr, iterations): the paper's laplacian settings and statfit's tuned ones (statfit.core.methods).
LAPLACIAN = {"paper": (19.0, 0.01, 500), "tuned": (300.0, 0.1, 1000)}
QUICK_ITERATIONS = 200
QUICK = ("jaw-open only; 200 laplacian iterations at the paper's λ and lr only; the default pipeline cut to "
         "500 iterations; 2 iterations per amberg step; no sumner; 10 CPD iterations")
# Match distance thresholds, in trimesh's normalised frame (chosen on jaw-open, see PEER_NOTES).
AMBERG_THRESHOLD = 0.05
SUMNER_THRESHOLD = 0.1
# trimesh's own default schedules, written out so the report can state them.
AMBERG_STEPS = [[0.01, 10, 0.5, 10], [0.02, 5, 0.5, 10], [0.03, 2.5, 0.5, 10], [0.01, 0, 0.0, 10]]
SUMNER_STEPS = [[1, 0.001, 1.0, 1000, 0], [1, 0.001, 1.0, 1000, 0], [10, 0.001, 1.0, 1000, 0],
                [100, 0.001, 1.0, 1000, 0]]
# Coherent point drift: kernel width β and regularisation α in unit-frame units (chosen on jaw-open,
# see PEER_NOTES), outlier weight w, and the control vertices that carry the motion field.
CPD = {"alpha": 20.0, "beta": 0.05, "w": 0.1, "sigma2": 0.01, "controls": 1000, "iterations": 50, "tolerance": 1e-6}

INTRO = """Template → partial scan (4,300 points, the registration cases), each fit in a fresh process with
{threads} torch threads (numpy/scipy use their default, all cores), device {device}; errors are mean
vertex errors divided by the target's RMS radius; mode {mode}.

**(a) largesteps vs statfit `laplacian`.** Both loops minimise statfit's `ScanObjective` (closest
points refreshed every 10 iterations, 5 % trim) in statfit's unit frame from the template, with the
same λ, lr, betas (0.9, 0.999) and iteration count. largesteps: `compute_matrix(x0, faces, λ)` (uniform
Laplacian, M = I + λL), u₀ = `to_differential(M, x0)`, x = `from_differential(M, u)` (Cholesky, its
backward is the second solve), `AdamUniform`, the loop of the package's README. statfit: the library's
`laplacian` method, x = x₀ + (I + λL)⁻¹u with u₀ = 0, `UniformAdam`, through `run_fit`. Set-up = the
matrix and its factorisation; ms / iteration = the loop's wall time / iterations."""

LARGESTEPS_NOTES = """The two follow the same trajectory: the map is linear, so x₀ + M⁻¹u (u₀ = 0) and M⁻¹u (u₀ = Mx₀)
receive the same gradients M⁻¹∂L/∂x and the same AdamUniform steps (largesteps' ε 1e-8 is added to
max √v̂, statfit's to √max v̂: the same number); `compute_matrix` without `alpha` is I + λL with the
combinatorial Laplacian D − A, as in `statfit.core.laplacian`. The remaining difference is float32
round-off (M⁻¹Mx₀ ≠ x₀ by ~1e-7, then carried along the trajectory: ~1e-6 after 500 iterations,
up to 2e-5 radii after 1000 at λ 300). Notes: largesteps 0.2.2's `compute_matrix` hard-codes
device='cuda', so on the CPU its own code runs with `torch.arange`/`torch.ones` redirected to the CPU;
statfit's loop flushes subnormal floats (`run_fit`), the largesteps loop runs as the package's users
write it."""

PEER_NOTES = """**Settings, and why they are fair.** All peers start from the same template in statfit's unit
frame (trimesh normalises by the template's bounding box itself, so its thresholds are unit-free
anyway); none gets landmarks or a model.

- `trimesh.registration.nricp_amberg` (Amberg et al. 2007): trimesh's default schedule
  (ws, wl, wn, iterations) = {amberg}, `distance_threshold` {amberg_threshold} (in trimesh's normalised frame, the
  template's bounding-box diagonal = 1). The target is a point cloud: `use_faces=False` (trimesh 5.2
  asks a `PointCloud` for faces otherwise), matches from a k-d tree, normals estimated from 8
  neighbours (`use_vertex_normals` only applies to mesh targets). Tried on jaw-open (one run each, loaded
  machine; all / observed / unobserved): threshold 0.1 (trimesh's default) 0.143 / 0.088 / 0.275,
  0.2 0.143 / 0.088 / 0.273, **0.05 0.133 / 0.085 / 0.246** (kept), and a stiff-to-soft schedule
  ws 1 → 0.3 → 0.1 → 0.03 → 0.01 (Amberg's paper's shape) 0.153 / 0.093 / 0.296; the template is
  0.151 / 0.138 / 0.183. It fits the observed side well but bends the unseen side away.
- `trimesh.registration.nricp_sumner` (Sumner & Popović 2004): trimesh's default schedule
  (wc, wi, ws, wl, wn) = {sumner}, `distance_threshold` {sumner_threshold} (trimesh's default; jaw-open 0.131 / 0.084 / 0.242 in
  68 s on the loaded machine, a little better than amberg; no other setting tried for lack of time).
- `pycpd.DeformableRegistration` (coherent point drift, Myronenko & Song 2010), Y = template, X = scan,
  in the unit frame: α {alpha}, β {beta} (kernel width, in RMS radii), w {w} (outlier weight), initial σ²
  {sigma2} (None: pycpd's estimate), at most {iterations} iterations, tolerance {tolerance}. pycpd 2.0 has no low-rank
  option: G, diag(P1)·G and the solve are dense M×M, O(M³) per iteration (M = 11,248 vertices: 1 GB
  each, about a minute an iteration here), so CPD moves {controls} random template vertices and every
  vertex follows CPD's own motion field v(z) = Σₖ G(z, yₖ) wₖ. Tried on jaw-open (500 controls, 30
  iterations): with pycpd's initial σ² (≈ the squared scan–template spread) the template first
  slides towards the one-sided scan's centroid and never recovers, 0.50–0.72 over α ∈ {{2, 20}},
  β ∈ {{0.1, 0.3}}, w ∈ {{0.1, 0.5}}; starting at σ² 0.01 (the template already lies within ~0.15
  radii of the scan, as the nricp thresholds assume) 0.21–0.27 on the same grid (w makes no
  difference), α 100 / β 0.1 0.195, **α 20 / β 0.05 0.180** (kept), α 20 / β 0.1 with 1500 controls 0.173: CPD matches point densities,
  so a partial scan, every point of which must be explained by the template, pulls the template's
  unseen parts in; no setting tried beat the template (0.151)."""


@dataclass
class Fit:
    """Fitted vertices (unit frame) with the set-up (matrix, factorisation) and loop seconds."""

    vertices: np.ndarray
    setup_s: float
    loop_s: float


def scan_objective(faces: np.ndarray, num_vertices: int, points: np.ndarray, device: str) -> ScanObjective:
    """statfit's point-to-surface term (refresh every 10 iterations, 5 % trim) on ``points`` (unit frame)."""
    scan = torch.as_tensor(points, dtype=torch.float32, device=device)
    return ScanObjective(scan, ClosestPointQuery(faces, num_vertices, k=2, device=torch.device(device)))


def statfit_laplacian(template: np.ndarray, faces: np.ndarray, points: np.ndarray, lam: float, lr: float,
                      iterations: int, device: str = "cpu") -> Fit:
    """statfit's laplacian method (x = x0 + (I + λL)⁻¹ u, UniformAdam) through its own fit loop."""
    objective = scan_objective(faces, len(template), points, device)
    x0 = torch.as_tensor(template, dtype=torch.float32, device=device)
    start = time.perf_counter()
    space = FitSpace(x0, torch.empty(0, x0.numel(), device=device), torch.empty(0, device=device), faces)
    param, optimizer = build(Settings("laplacian", iterations, lr, lam=lam), space, x0)
    setup = time.perf_counter() - start
    result = run_fit(param, optimizer, objective, iterations)
    return Fit(result.vertices.cpu().double().numpy(), setup, result.seconds)


class _TorchOn:
    """``torch`` with the device of ``arange`` and ``ones`` forced: largesteps 0.2.2's
    ``compute_matrix`` hard-codes device='cuda', so on the CPU its code runs with this in its place."""

    def __init__(self, device: str):
        self.device = device

    def __getattr__(self, name: str) -> Any:
        attr = getattr(torch, name)
        if name in ("arange", "ones"):
            return lambda *args, **kwargs: attr(*args, **(kwargs | {"device": self.device}))
        return attr


def largesteps_laplacian(template: np.ndarray, faces: np.ndarray, points: np.ndarray, lam: float, lr: float,
                         iterations: int, device: str = "cpu") -> Fit:
    """Nicolet et al.'s loop with their package: M = compute_matrix (I + λL, uniform), u₀ = M x₀,
    x = from_differential(M, u) (Cholesky, differentiable), AdamUniform on u."""
    import largesteps.geometry
    from largesteps.optimize import AdamUniform
    from largesteps.parameterize import from_differential, to_differential

    objective = scan_objective(faces, len(template), points, device)
    x0 = torch.as_tensor(template, dtype=torch.float32, device=device)
    start = time.perf_counter()
    with mock.patch.object(largesteps.geometry, "torch", _TorchOn(device)):
        matrix = largesteps.geometry.compute_matrix(x0, torch.as_tensor(faces, dtype=torch.long, device=device), lam)
    u = to_differential(matrix, x0).requires_grad_(True)
    from_differential(matrix, u.detach())  # factorises (cached per matrix)
    optimizer = AdamUniform([u], lr=lr, betas=(0.9, 0.999))
    setup = time.perf_counter() - start
    start = time.perf_counter()
    for it in range(iterations):
        x = from_differential(matrix, u)
        objective.prepare(x, it)
        loss = objective(x)["data"]
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    loop = time.perf_counter() - start
    return Fit(from_differential(matrix, u).detach().cpu().double().numpy(), setup, loop)


def nricp(template: np.ndarray, faces: np.ndarray, points: np.ndarray, algorithm: str,
          steps: list[list[float]], distance_threshold: float) -> np.ndarray:
    """trimesh's ``nricp_amberg`` or ``nricp_sumner`` of the template onto the point cloud. With a
    point-cloud target, use_faces must be False (trimesh 5.2 would ask the cloud for faces): the
    matches come from a k-d tree and the target normals are estimated from 8 neighbours."""
    import trimesh
    from trimesh import registration

    source = trimesh.Trimesh(template, faces, process=False)
    fit = getattr(registration, f"nricp_{algorithm}")
    return np.asarray(fit(source, trimesh.PointCloud(points), steps=steps, distance_threshold=distance_threshold,
                          use_faces=False, use_vertex_normals=False))


def cpd(template: np.ndarray, points: np.ndarray, alpha: float, beta: float, w: float, sigma2: float | None,
        controls: int, iterations: int, tolerance: float) -> np.ndarray:
    """pycpd's DeformableRegistration of ``controls`` random template vertices onto the scan; every
    vertex then moves by CPD's motion field v(z) = Σₖ exp(−|z − yₖ|²/2β²) wₖ. (pycpd 2.0 has no
    low-rank option: its G, diag(P1)·G and solve are dense M×M, O(M³) a step.)"""
    from pycpd import DeformableRegistration

    ids = np.random.default_rng(0).choice(len(template), min(controls, len(template)), replace=False)
    reg = DeformableRegistration(X=points, Y=template[ids], alpha=alpha, beta=beta, w=w, sigma2=sigma2,
                                 max_iterations=iterations, tolerance=tolerance)
    reg.register()
    kernel = np.exp(-((template[:, None, :] - template[None, ids, :]) ** 2).sum(-1) / (2 * beta**2))
    return template + kernel @ reg.W


def measure(case_name: str, tool: str, settings: dict[str, Any], device: str = "cpu") -> dict[str, Any]:
    """One fit of ``tool`` on the named scan case (run in a child process): relative errors, wall
    time of the fit and, for the laplacian pair, set-up / per-iteration times and the vertices."""
    model, case = ict_model(), scan_case(case_name)
    frame = Frame.of(model.template)
    template, points = frame.to_unit(model.template), frame.to_unit(case.points)
    extra: dict[str, Any] = {}
    start = time.perf_counter()
    if tool == "statfit":
        vertices = register(model, case.points, settings["method"], preset=settings["preset"], device=device,
                            iterations=settings.get("iterations")).vertices
    elif tool in ("statfit-laplacian", "largesteps"):
        run = statfit_laplacian if tool == "statfit-laplacian" else largesteps_laplacian
        fit = run(template, model.faces, points, settings["lam"], settings["lr"], settings["iterations"], device)
        vertices = frame.from_unit(fit.vertices)
        extra = {"setup_s": fit.setup_s, "ms_per_iteration": 1e3 * fit.loop_s / settings["iterations"],
                 "unit_vertices": fit.vertices.tolist()}
    elif tool in ("amberg", "sumner"):
        vertices = frame.from_unit(nricp(template, model.faces, points, tool, settings["steps"],
                                         settings["distance_threshold"]))
    elif tool == "cpd":
        vertices = frame.from_unit(cpd(template, points, **settings))
    else:
        raise ValueError(f"unknown tool {tool!r}")
    seconds = time.perf_counter() - start
    return {"case": case_name, "tool": tool, "settings": settings, "seconds": seconds,
            "errors": relative_errors(vertices, case.target, case.observed)} | extra


def template_errors(case_name: str) -> dict[str, float]:
    """The unfitted template's relative errors (the starting point of every tool)."""
    case = scan_case(case_name)
    return relative_errors(ict_model().template, case.target, case.observed)


def _jobs(quick: bool) -> list[tuple[str, dict[str, Any]]]:
    """(tool, settings) per fit on one case; shortened as QUICK says when ``quick``."""
    presets = {"paper": LAPLACIAN["paper"]} if quick else LAPLACIAN
    jobs: list[tuple[str, dict[str, Any]]] = [
        (tool, {"preset": preset, "lam": lam, "lr": lr, "iterations": QUICK_ITERATIONS if quick else iterations})
        for preset, (lam, lr, iterations) in presets.items() for tool in ("statfit-laplacian", "largesteps")]
    jobs += [("statfit", {"method": "default", "preset": "tuned", "iterations": 500 if quick else None}),
             ("amberg", {"steps": [s[:3] + [2] for s in AMBERG_STEPS] if quick else AMBERG_STEPS,
                         "distance_threshold": AMBERG_THRESHOLD}),
             ("cpd", CPD | {"iterations": 10} if quick else CPD)]
    if not quick:
        jobs += [("statfit", {"method": "laplacian", "preset": "paper"}),
                 ("sumner", {"steps": SUMNER_STEPS, "distance_threshold": SUMNER_THRESHOLD})]
    return jobs


def _label(result: dict[str, Any]) -> str:
    settings = result["settings"]
    if result["tool"] == "statfit":
        return f"statfit {settings['method']} ({settings['preset']})"
    if result["tool"] in ("statfit-laplacian", "largesteps"):
        return f"{result['tool']} ({settings['preset']}: λ {settings['lam']:g}, lr {settings['lr']:g}, " \
               f"{settings['iterations']} it)"
    return {"amberg": "trimesh nricp_amberg", "sumner": "trimesh nricp_sumner", "cpd": "pycpd deformable"}[result["tool"]]


def measure_all(quick: bool, device: str = "cpu") -> dict:
    """All peers on the scan cases (quick: jaw-open only, shorter runs, see ``_jobs``), each tool's
    run by :func:`measure` in a fresh process."""
    cases = ["jaw-open"] if quick else list(SCAN_CASES)
    results, template, pairs = [], {}, []
    for name in cases:
        template[name] = template_errors(name)
        case_results = []
        for tool, settings in _jobs(quick):
            case_results.append(in_child("peers", "measure", name, tool, settings, device, threads=THREADS))
            print(f"peers: {name} {tool} {case_results[-1]['seconds']:.1f} s", file=sys.stderr, flush=True)
        laplacian = {(r["tool"], r["settings"]["preset"]): r for r in case_results if "unit_vertices" in r}
        for preset in dict.fromkeys(preset for _, preset in laplacian):
            ours, theirs = laplacian["statfit-laplacian", preset], laplacian["largesteps", preset]
            diff = np.abs(np.asarray(ours.pop("unit_vertices")) - np.asarray(theirs.pop("unit_vertices"))).max()
            pairs.append((name, ours, theirs, float(diff)))
        results += case_results
    return {"quick": quick, "device": device, "template": template, "results": results,
            "laplacian_max_difference": [[n, o["settings"], d] for n, o, _, d in pairs]}


def run(quick: bool, device: str = "cpu", image_dir: Path | None = None) -> Section:
    return section(measure_all(quick, device))


def section(data: dict) -> Section:
    """The tables of :func:`measure_all`'s results (also from a saved results file)."""
    quick, device, template, results = data["quick"], data["device"], data["template"], data["results"]
    cases = list(template)

    def laplacian_run(name: str, tool: str, settings: dict) -> dict:
        return next(r for r in results if r["case"] == name and r["tool"] == tool
                    and r["settings"]["preset"] == settings["preset"])

    pairs = [(name, laplacian_run(name, "statfit-laplacian", settings), laplacian_run(name, "largesteps", settings),
              diff) for name, settings, diff in data["laplacian_max_difference"]]
    pair_rows = [[name, _label(r), r["errors"]["all"], r["errors"]["observed"], r["errors"]["unobserved"],
                  r["setup_s"], r["ms_per_iteration"], diff]
                 for name, ours, theirs, diff in pairs for r in (ours, theirs)]
    rows = [[name, "template (no fit)", e["all"], e["observed"], e["unobserved"], "", ""]
            for name, e in template.items()]
    rows += [[r["case"], _label(r), r["errors"]["all"], r["errors"]["observed"], r["errors"]["unobserved"],
              r["seconds"], r["peak_rss_mb"]] for r in results]
    rows.sort(key=lambda row: cases.index(row[0]))
    markdown = "\n\n".join([
        INTRO.format(mode=f"quick: {QUICK}" if quick else "full: the three scan cases", threads=THREADS,
                     device=device),
        markdown_table(["case", "loop", "all", "observed", "unobserved", "set-up s", "ms / iteration",
                        "max |Δx| (radii)"], pair_rows),
        LARGESTEPS_NOTES,
        markdown_table(["case", "tool", "all", "observed", "unobserved", "wall s", "peak RSS MB"], rows),
        PEER_NOTES.format(amberg=AMBERG_STEPS, amberg_threshold=AMBERG_THRESHOLD, sumner=SUMNER_STEPS,
                          sumner_threshold=SUMNER_THRESHOLD, **CPD)])
    return Section("peers", "Peers on the scan cases", markdown, data=data)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--json", type=str, help="also save the raw numbers here")
    args = parser.parse_args()
    section = run(args.quick, args.device)
    print(section.markdown)
    if args.json:
        save_json(Path(args.json), section.data)


if __name__ == "__main__":
    main()
