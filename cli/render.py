"""``statfit render``: fit the model's template to one normal map (inverse rendering)."""
from __future__ import annotations

from pathlib import Path

import typer

from statfit.errors import StatfitError
from statfit.io.files import check_writable, mesh_format, params_suffix
from statfit.objectives.weights import SILHOUETTE_WEIGHT
from statfit_cli.common import (BetaOption, DeviceOption, IterationsOption, JsonOption, KOption, LamOption,
                                LaplacianOption, LogOption, LrOption, MethodOption, ModeGainOption, ModelOption,
                                ParamsOption, PowerOption, PresetOption, QuietOption, RigidModesOption, SeedOption,
                                SilhouetteOption, ThreadsOption, check_preview, printed_warnings, refuse_missing,
                                refuse_overwrite, setting_overrides, within)


def render(
    normal_map_path: Path = typer.Argument(..., metavar="NORMALS.EXR", help="Normal map: OpenEXR with R, G, B = unit "
                                           "normal and A = coverage (or a render's Normal.X/Y/Z pass), or an 8- or "
                                           "16-bit PNG holding (n + 1) / 2 (background: alpha, or black, white or grey; "
                                           "give --camera) (docs/formats.md).",
                                           show_default=False),
    camera_path: Path = typer.Option(None, "--camera", "-c", help="Camera JSON (width, height, K, world_to_camera; "
                                     "or camera_to_world, as NeRF and Blender give it, with \"convention\": "
                                     "\"opengl\"; docs/formats.md). Default: the camera in the EXR header.",
                                     show_default=False),
    model_path: Path = ModelOption,
    k: int = KOption,
    method: str = MethodOption,
    preset: str = PresetOption,
    out: Path = typer.Option(None, "--out", "-o", help="Fitted mesh (.ply or .obj). Default: <normals>_fit.ply here.",
                             show_default=False),
    log: Path = LogOption,
    preview: Path = typer.Option(None, help="PNG: target and fitted normals, angular error, a second view.",
                                 show_default=False),
    preview_colour: str = typer.Option("normals", "--preview-colour", help="What the preview's two other views "
                                       "show: normals, or where the fit guessed: data_distance, off_span or observed "
                                       "(the fitted PLY's fields, in colour)."),
    params: Path = ParamsOption,
    align: str = typer.Option("rigid", help="Initial alignment: rigid (the model's coefficients, with a rotation and "
                              "a move parallel to the image where they lower the objective by 10%), similarity "
                              "(also a scale), or none (start from the template as it is)."),
    init: Path = typer.Option(None, help="Start from this mesh (the model's topology, the camera's world frame) "
                              "instead of the template.", show_default=False),
    normal_space: str = typer.Option("world", help="Frame of the map's normals: world or camera."),
    normal_convention: str = typer.Option("opencv", help="Axes of camera-space normals: opencv (x right, y down, "
                                          "z forward) or opengl (x right, y up, z towards the viewer)."),
    mask: Path = typer.Option(None, help="Mask image (white = foreground) replacing the EXR's alpha.",
                              show_default=False),
    silhouette_weight: float = typer.Option(SILHOUETTE_WEIGHT, help="Weight of the silhouette term (0: off).",
                                            callback=within(0, 1e6)),
    silhouette: str = SilhouetteOption,
    rigid_modes: str = RigidModesOption,
    region: str = typer.Option(None, "--region", metavar="<name>",
                               help="Fit only the model's region NAME (e.g. face): after the "
                               "alignment, only pixels showing the region's triangles count and the silhouette is "
                               "not used; the rest of the mesh follows the model's prior.", show_default=False),
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
    quiet: bool = QuietOption,
    json_out: bool = JsonOption,
) -> None:
    """Inverse rendering: deform the model's template until its rendered normals and silhouette
    match a normal map seen from a known camera.

    The output mesh has the template's topology and vertex order, in the camera's world frame.
    Example:

        \b
        statfit render normals.exr --camera camera.json --model model.npz --out fit.ply --preview fit.png
        statfit render normals.exr --params fit.params.json --preview fit.png --preview-colour data_distance
        statfit render estimated.png --camera camera.json --normal-space camera --normal-convention opengl

    The PLY's vertices carry data_distance (to the nearest covered pixel's point on the fit),
    observed (0/1: seen in a covered pixel) and off_span (distance from the model's span), in the
    camera's world units (docs/formats.md).
    """
    out = out or Path(f"{normal_map_path.stem}_fit.ply")
    check_preview(preview, preview_colour)
    if params is not None:
        params_suffix(params)
    for target in (out, log, preview, params):
        if target is not None:
            check_writable(target)
    mesh_format(out)
    refuse_missing({"normal map": normal_map_path, "camera file": camera_path, "mask": mask, "file": init},
                   model_path)
    refuse_overwrite({"--out": out, "--log": log, "--preview": preview, "--params": params},
                     {"normal map": normal_map_path, "camera file": camera_path, "mask": mask, "start mesh": init,
                      "model": model_path})

    # The library loads once the paths are known good: a mistyped name is refused at once.
    from statfit.core.device import resolve_device
    from statfit.geometry.support import view_support
    from statfit.io.image import read_mask
    from statfit.io.mesh import mesh_bytes, read_mesh
    from statfit.io.normalmap import apply_mask, camera_for_map, read_normal_map
    from statfit.model.cut import check_rigid_modes
    from statfit.model.importers.cache import open_model
    from statfit.model.params import project, vertex_fields
    from statfit.model.params_file import params_bytes
    from statfit.render.job import camera_space_normals, reconstruct, render_stages, silhouette_sides
    from statfit_cli.runner import finish, fit_run

    overrides = setting_overrides(iterations, lr, beta, power, lam, laplacian, mode_gain)
    check_rigid_modes(rigid_modes)
    stages = render_stages(method, preset, region, **overrides)
    torch_device = resolve_device(device, "render")
    with printed_warnings():
        normal_map = read_normal_map(normal_map_path)
    if mask is not None:
        normal_map = apply_mask(normal_map, read_mask(mask), str(mask))
    camera = camera_for_map(normal_map, camera_path, normal_map_path)
    model = open_model(model_path, k)
    start = None
    if init is not None:
        start, faces = read_mesh(init)
        if faces.shape != model.faces.shape or (faces != model.faces).any():
            raise StatfitError(f"{init} does not have the model's topology")
    header = dict(method=method, preset=preset, stages=[s.describe() for s in stages], model=model.source,
                  modes=model.num_modes, input=str(normal_map_path), camera=camera.to_dict(),
                  pixels=int(normal_map.mask.sum()), align=align, init=str(init) if init else None,
                  normal_space=normal_space, normal_convention=normal_convention,
                  silhouette_weight=silhouette_weight, silhouette=silhouette_sides(silhouette, model), region=region,
                  rigid_modes=rigid_modes, device=str(torch_device), threads=threads, seed=seed)
    with fit_run("render", log, normal_map_path.name, sum(s.iterations for s in stages), quiet, **header) as run:
        result = reconstruct(model, normal_map, camera, stages=stages, normal_space=normal_space,
                             normal_convention=normal_convention, align=align, init=start,
                             device=str(torch_device), silhouette_weight=silhouette_weight, seed=seed,
                             on_record=run.on_record, region=region, threads=threads, silhouette=silhouette,
                             rigid_modes=rigid_modes)
    summary = {"input": str(normal_map_path), "output": str(out), "method": method, "iterations": result.iterations,
               "final_loss": result.loss, "seconds": result.seconds, "threads": result.threads,
               "stage_seconds": result.stage_seconds, "model_to_world": result.transform.as_matrix().tolist()}
    projection = project(model, result.vertices, result.transform)
    fields = vertex_fields(projection, *view_support(result.vertices, model.faces, [(camera, normal_map.mask)]))
    outputs = {out: mesh_bytes(result.vertices, model.faces, mesh_format(out), fields)}
    if params is not None:
        outputs[params] = params_bytes(model, projection, params)
    if preview is not None:
        from statfit.render.preview import preview_png  # matplotlib is imported only when a preview is asked for
        target = camera_space_normals(normal_map, camera, normal_space, normal_convention)
        colour = None if preview_colour == "normals" else (preview_colour, fields[preview_colour])
        outputs[preview] = preview_png(target, normal_map.mask, result.vertices, model.faces, camera, colour)
    finish(run, summary, outputs, json_out)
