"""``statfit register``: fit the model's template to one partial scan (many: ``statfit batch``)."""
from __future__ import annotations

from pathlib import Path

import typer

from statfit.errors import StatfitError
from statfit.io.files import check_writable, mesh_format, params_suffix
from statfit_cli.common import (BetaOption, ClutterOption, DeviceOption, FallbackOption, IterationsOption,
                                JsonOption, KOption, LamOption, LandmarkWeightOption, LaplacianOption, LogOption,
                                LrOption, MethodOption, ModeGainOption, ModelOption, ParamsOption, PowerOption,
                                PresetOption, QuietOption, RigidModesOption, SeedOption, ThreadsOption,
                                check_preview, clutter_choice, refuse_missing, refuse_overwrite, setting_overrides,
                                within)


def register(
    scans: list[str] = typer.Argument(..., metavar="SCAN", help="Scan file: any point cloud or mesh (PLY, OBJ, STL, "
                                      "OFF), or a text point cloud (XYZ, ASC, CSV, TXT: rows starting x y z); '-' "
                                      "reads a PLY from standard input. For many scans: `statfit batch "
                                      "register`.", show_default=False),
    model_path: Path = ModelOption,
    k: int = KOption,
    method: str = MethodOption,
    preset: str = PresetOption,
    fallback: bool = FallbackOption,
    out: str = typer.Option(None, "--out", "-o", metavar="<path>",
                            help="Fitted mesh (.ply or .obj; '-' for PLY on stdout). "
                            "Default: <scan>_fit.ply here.", show_default=False),
    log: Path = LogOption,
    preview: Path = typer.Option(None, help="PNG: the scan's points over the fit, and the fit from the front, turned "
                                 "70° and from behind, coloured by --preview-colour.", show_default=False),
    preview_colour: str = typer.Option("data_distance", "--preview-colour", help="What the preview's views of the "
                                       "fit show: where it guessed — data_distance (to the nearest scan point), "
                                       "off_span or observed (the fitted PLY's fields, in colour) — or normals."),
    params: Path = ParamsOption,
    align: str = typer.Option("auto", help="Pre-alignment. auto: finds the scan's pose, scale and units (mm, cm, m; "
                              "a scan in inches: give --landmarks) without landmarks, and leaves a scan already on the model where it is; none: the scan "
                              "lies in the model's frame; rigid/similarity: ICP from the centroids."),
    region: str = typer.Option(None, "--region", metavar="<name>",
                               help="Fit only the model's region NAME (a region_NAME array in "
                               "the npz, e.g. face): scan points closest to other parts are ignored; the "
                               "rest of the mesh follows the model's prior.", show_default=False),
    landmarks: Path = typer.Option(None, "--landmarks", help="The scan's landmarks, one per model landmark in the "
                                   "model's order (missing: nan/null): text rows 'x y z', an iBUG .pts file (3D), or a "
                                   "JSON list of [x, y, z]. They place the start (a robust similarity: any pose, scale "
                                   "or units), which --align auto then polishes on the scan (rigid pose and every mode; "
                                   "none keeps it, rigid/similarity refine it by ICP), and stay a fit term.",
                                   show_default=False),
    landmark_weight: float = LandmarkWeightOption,
    clutter: str = ClutterOption,
    rigid_modes: str = RigidModesOption,
    device: str = DeviceOption,
    threads: int = ThreadsOption,
    seed: int = SeedOption,
    iterations: int = IterationsOption,
    lr: float = LrOption,
    beta: float = BetaOption,
    power: float = PowerOption,
    lam: float = LamOption,
    laplacian: str = LaplacianOption,
    mode_gain: float = ModeGainOption,
    refresh: int = typer.Option(10, help="Recompute closest surface points every N iterations.",
                                 callback=within(1, 100_000)),
    trim: float = typer.Option(0.05, help="Fraction of farthest scan points ignored (outlier robustness).",
                               callback=within(0, 0.99)),
    quiet: bool = QuietOption,
    json_out: bool = JsonOption,
) -> None:
    """Non-rigid registration: deform the model's template onto a partial scan.

    The scan may come in any pose and in mm, cm or m (found by --align auto; inches with
    --landmarks); a mesh scan's points are drawn by area. The output mesh has the template's topology and vertex order, in the
    scan's frame. Example:

        \b
        statfit register scan.ply --model model.npz --method statistical --out fit.ply --log fit.jsonl
        statfit register scan.ply --model flame.npz --region face --landmarks scan_landmarks.txt
        statfit register scan.ply --out fit.ply --params fit.params.json
        statfit register scan.xyz --out fit.ply --preview fit.png

    The PLY's vertices carry data_distance (to the nearest scan point), observed (0/1) and
    off_span (distance from the model's span), in the scan's units (docs/formats.md).
    """
    if len(scans) > 1:
        raise StatfitError(f"{len(scans)} scans given; register fits one — for many, `statfit batch register SCANS "
                           "--out-dir DIR` (parallel, resumable, one failure does not stop the rest)")
    scan = scans[0]
    target = out or ("-" if scan == "-" else f"{Path(scan).stem}_fit.ply")
    if json_out and target == "-":
        raise StatfitError("--json and --out - both want standard output; choose one")
    if params is not None:
        params_suffix(params)
    check_preview(preview, preview_colour)
    for path in (target, log, params, preview):
        if path is not None:
            check_writable(path)
    mesh_format(target)
    refuse_missing({"scan": scan, "landmark file": landmarks}, model_path)
    refuse_overwrite({"--out": target, "--log": log, "--preview": preview, "--params": params},
                     {"scan": scan, "landmark file": landmarks, "model": model_path})

    # The library loads once the paths are known good: a mistyped name is refused at once.
    from statfit.core.device import resolve_device
    from statfit.core.methods import fallback as method_fallback, landmark_weight as method_landmark_weight, resolve
    from statfit.geometry.support import scan_support
    from statfit.io.landmarks import read_landmarks
    from statfit.io.mesh import load_scan, mesh_bytes
    from statfit.model.cut import check_rigid_modes
    from statfit.model.importers.cache import open_model
    from statfit.model.params import project, vertex_fields
    from statfit.model.params_file import params_bytes
    from statfit.registration.job import register as fit_scan
    from statfit_cli.runner import finish, fit_run

    overrides = setting_overrides(iterations, lr, beta, power, lam, laplacian, mode_gain)
    clutter_rules = clutter_choice(clutter)
    check_rigid_modes(rigid_modes)
    stages = resolve(method, preset, **overrides)
    refit = method_fallback(method, preset, **overrides) if fallback else None
    weight = method_landmark_weight(method) if landmark_weight is None else landmark_weight
    torch_device = resolve_device(device, "register")
    model = open_model(model_path, k)
    scan_landmarks = read_landmarks(landmarks) if landmarks is not None else None
    points = load_scan(scan, seed)
    header = dict(method=method, preset=preset, stages=[s.describe() for s in stages], model=model.source,
                  modes=model.num_modes, input=scan, points=len(points.points), align=align, device=str(torch_device),
                  threads=threads, seed=seed, refresh=refresh, trim=trim, region=region,
                  landmarks=str(landmarks) if landmarks else None, landmark_weight=weight,
                  clutter=clutter, rigid_modes=rigid_modes)
    label = Path(scan).name if scan != "-" else "stdin"
    with fit_run("register", log, label, sum(s.iterations for s in stages), quiet, **header) as run:
        result = fit_scan(model, points, stages=stages, align=align, device=str(torch_device),
                          refresh_every=refresh, trim=trim, seed=seed, on_record=run.on_record,
                          region=region, landmarks=scan_landmarks, landmark_weight=landmark_weight, threads=threads,
                          clutter=clutter_rules, fallback=refit, rigid_modes=rigid_modes)
    summary = {"input": scan, "output": target, "method": method, "iterations": result.iterations,
               "final_loss": result.loss, "seconds": result.seconds, "threads": result.threads,
               "stage_seconds": result.stage_seconds, "model_to_scan": result.transform.as_matrix().tolist(),
               "pose": result.pose, "fallback": result.fallback}
    projection = project(model, result.vertices, result.transform, (result.pose or {}).get("units_factor"))
    fields = vertex_fields(projection, *scan_support(result.vertices, points.points))
    outputs = {target: mesh_bytes(result.vertices, model.faces, mesh_format(target), fields)}
    if params is not None:
        outputs[params] = params_bytes(model, projection, params)
    if preview is not None:
        from statfit.registration.preview import register_preview_png  # matplotlib: only for a preview
        colour = None if preview_colour == "normals" else (preview_colour, fields[preview_colour])
        outputs[preview] = register_preview_png(result.vertices, model.faces, points.points,
                                                result.transform.as_matrix()[:3, :3], colour)
    finish(run, summary, outputs, json_out)
