"""``statfit register``: fit the model's template to one or more partial scans."""
from __future__ import annotations

import json
import time
from pathlib import Path

import typer

from statfit.errors import StatfitError
from statfit.io.jsonlog import JsonLinesLog, versions
from statfit.io.mesh import check_writable, mesh_bytes, mesh_format, read_points, write_atomic
from statfit.methods import resolve
from statfit.register import register as fit_scan, resolve_device
from statfit_cli.common import KOption, ModelOption, open_model, printed_warnings, progress_bar


def _targets(scans: list[str], out: str | None, out_dir: Path | None, log: Path | None
             ) -> list[tuple[str, str, Path | None]]:
    """(scan, mesh output, log output) for every scan."""
    if out_dir is not None:
        if out is not None or log is not None:
            raise StatfitError("use either --out/--log (one scan) or --out-dir (many scans), not both")
        if "-" in scans:
            raise StatfitError("--out-dir cannot be used with a scan read from standard input")
        stems = [Path(s).stem for s in scans]
        if len(set(stems)) != len(stems):
            raise StatfitError("two scans share a file name; their outputs would collide in --out-dir")
        return [(s, str(out_dir / f"{stem}.ply"), out_dir / f"{stem}.jsonl") for s, stem in zip(scans, stems)]
    if len(scans) > 1:
        raise StatfitError("several scans need --out-dir")
    scan = scans[0]
    default = "-" if scan == "-" else f"{Path(scan).stem}_fit.ply"
    return [(scan, out or default, log)]


def register(
    scans: list[str] = typer.Argument(..., help="Scan file(s): any point cloud or mesh (PLY, OBJ, STL, OFF); "
                                      "'-' reads a PLY from standard input.", show_default=False),
    model_path: Path = ModelOption,
    k: int = KOption,
    method: str = typer.Option("default", help="default (the measured best pipeline), statistical, hybrid, "
                               "laplacian, pca, regularized or none."),
    preset: str = typer.Option("tuned", help="tuned (our measured defaults) or paper (Nicolet-style "
                               "settings of the paper, exactly)."),
    out: str = typer.Option(None, "--out", "-o", help="Fitted mesh (.ply or .obj; '-' for PLY on stdout). "
                            "Default: <scan>_fit.ply here.", show_default=False),
    out_dir: Path = typer.Option(None, help="Folder for many scans: <scan>.ply and <scan>.jsonl each.",
                                 show_default=False),
    log: Path = typer.Option(None, help="JSON-lines log: header, a record every 10 iterations, summary.",
                             show_default=False),
    align: str = typer.Option("none", help="Pre-alignment: none, rigid or similarity (ICP; similarity also "
                              "estimates scale, e.g. for a scan in other units)."),
    device: str = typer.Option("cpu", help="auto, cpu or cuda."),
    seed: int = typer.Option(0, help="Random seed; the same seed gives the same mesh."),
    iterations: int = typer.Option(None, help="Iterations (all stages together). Default: the method's.",
                                   show_default=False),
    lr: float = typer.Option(None, help="Step size (fit frame: model centred, unit RMS radius).", show_default=False),
    beta: float = typer.Option(None, help="β of the statistical/hybrid filter, or the regulariser's weight.",
                               show_default=False),
    power: float = typer.Option(None, help="Exponent p on the statistical filter (same as β' = (1+β)^p − 1).",
                                show_default=False),
    lam: float = typer.Option(None, help="λ of the Laplacian (laplacian, hybrid).", show_default=False),
    laplacian: str = typer.Option(None, help="uniform or cotangent.", show_default=False),
    mode_gain: float = typer.Option(None, help="γ: filter gain on mode j = (std_j/std_1)^γ; 0 is the paper's filter.",
                                    show_default=False),
    refresh: int = typer.Option(10, help="Recompute closest surface points every N iterations."),
    trim: float = typer.Option(0.05, help="Fraction of farthest scan points ignored (outlier robustness)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
    json_out: bool = typer.Option(False, "--json", help="Print each fit's summary as a JSON line on stdout."),
) -> None:
    """Non-rigid registration: deform the model's template onto a partial scan.

    The output mesh has the template's topology and vertex order. Example:

        statfit register scan.ply --model model.npz --method statistical --out fit.ply --log fit.jsonl
    """
    if laplacian is not None and laplacian not in ("uniform", "cotangent"):
        raise StatfitError(f"unknown Laplacian {laplacian!r}; choose uniform or cotangent")
    if not 0 <= trim < 1:
        raise StatfitError("--trim must lie in [0, 1)")
    if refresh < 1:
        raise StatfitError("--refresh must be at least 1")
    overrides = dict(iterations=iterations, lr=lr, beta=beta, power=power, lam=lam, laplacian=laplacian,
                     mode_gain=mode_gain)
    stages = resolve(method, preset, **overrides)
    torch_device = resolve_device(device)
    targets = _targets(scans, out, out_dir, log)
    if json_out and any(target == "-" for _, target, _ in targets):
        raise StatfitError("--json and --out - both want standard output; choose one")
    if out_dir is not None and not out_dir.is_dir():
        raise StatfitError(f"output folder does not exist: {out_dir}")
    for _, target, log_path in targets:
        check_writable(target)
        if log_path is not None:
            check_writable(log_path)
    for scan in scans:
        if scan != "-" and not Path(scan).is_file():
            raise StatfitError(f"scan not found: {scan}")
    model = open_model(model_path, k)
    total = sum(s.iterations for s in stages)
    for scan, target, log_path in targets:
        points = read_points(scan)
        started = time.perf_counter()
        record = JsonLinesLog(log_path)
        record.write("header", command="register", method=method, preset=preset,
                     stages=[s.describe() for s in stages], model=model.source, modes=model.num_modes,
                     input=scan, points=len(points), align=align, device=str(torch_device), seed=seed,
                     refresh=refresh, trim=trim, versions=versions())
        with progress_bar(total, Path(scan).name if scan != "-" else "stdin", not quiet) as advance:
            def on_record(iteration: int, terms: dict[str, float]) -> None:
                advance(iteration, terms)
                record.write("record", iteration=iteration, **terms, elapsed=time.perf_counter() - started)

            with printed_warnings():
                result = fit_scan(model, points, stages=stages, align=align, device=str(torch_device),
                                  refresh_every=refresh, trim=trim, seed=seed, on_record=on_record)
        summary = {"input": scan, "output": target, "method": method, "iterations": total,
                   "final_loss": result.loss, "seconds": result.seconds,
                   "stage_seconds": result.stage_seconds, "model_to_scan": result.transform.as_matrix()}
        record.write("summary", **summary)
        write_atomic(target, mesh_bytes(result.vertices, model.faces, mesh_format(target)))
        record.close()
        if json_out:
            print(json.dumps(summary))
