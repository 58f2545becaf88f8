"""``statfit splat`` (fit a model with splats bound to it to photographs) and ``statfit splat-render``
(render such splats from any camera)."""
from __future__ import annotations

import json
from pathlib import Path

from typing import TYPE_CHECKING

import numpy as np
import typer

from statfit.errors import StatfitError
from statfit.io.files import check_writable, existing_file, mesh_format, output_suffix, params_suffix
from statfit.objectives.weights import MASK_WEIGHT
if TYPE_CHECKING:
    from statfit.structures.camera import Camera
from statfit_cli.common import (BetaOption, DeviceOption, IterationsOption, JsonOption, KOption, LamOption,
                                LaplacianOption, LogOption, LrOption, MethodOption, ModeGainOption, ModelOption,
                                ParamsOption, PowerOption, PresetOption, QuietOption, SeedOption, ThreadsOption,
                                check_preview, refuse_missing, refuse_overwrite, setting_overrides, within)

MAX_CAMERA_BYTES = 16 << 20


def splat(
    folder: Path = typer.Argument(..., metavar="VIEWS", help="Folder with cameras.json and the photographs it names "
                                  "(docs/formats.md; `statfit synth views` makes one).", show_default=False),
    model_path: Path = ModelOption,
    k: int = KOption,
    method: str = MethodOption,
    preset: str = PresetOption,
    out: Path = typer.Option(Path("splat_fit.ply"), "--out", "-o", help="Fitted mesh (.ply or .obj)."),
    splats_out: Path = typer.Option(None, "--splats", help="Splats bound to the fitted mesh (PLY; "
                                    "`statfit splat-render` draws them).", show_default=False),
    preview: Path = typer.Option(None, help="PNG: a held-out view's photograph, the splats, their error and the "
                                 "fitted mesh.", show_default=False),
    log: Path = LogOption,
    params: Path = ParamsOption,
    per_triangle: int = typer.Option(1, help="Splats per triangle: 1, 3 or 4."),
    views_per_step: int = typer.Option(1, help="Training views rendered per iteration.", callback=within(1, 1000)),
    mask_weight: float = typer.Option(MASK_WEIGHT, help="Weight of the mask term (rendered opacity vs the views' "
                                      "alpha; 0: off).", callback=within(0, 1e6)),
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
    """Fit the model's template to photographs from known cameras with 2D Gaussian splats bound to
    its triangles (L1 + D-SSIM, as 3D Gaussian splatting); the vertices move through the method's
    filter, the splats' colours, opacities and sizes are fitted with them. Views marked 'test'
    are held out and scored (PSNR, SSIM) after the fit.

        \b
        statfit synth views --model model.npz --seed 2 --views 24 --size 256 --out views/
        statfit splat views/ --model model.npz --out fit.ply --splats splats.ply --preview fit.png
        statfit splat views/ --out fit.ply --params fit.params.json

    The PLY's vertices carry data_distance (to the nearest point of the fit seen in a training
    view's foreground), observed (0/1) and off_span (distance from the model's span).
    """
    if params is not None:
        params_suffix(params)
    check_preview(preview)
    if splats_out is not None:
        output_suffix(splats_out, (".ply",), "a splat file")
    for target in (out, splats_out, preview, log, params):
        if target is not None:
            check_writable(target)
    mesh_format(out)
    refuse_missing({}, model_path, folders={"views folder": folder})
    refuse_overwrite({"--out": out, "--splats": splats_out, "--preview": preview, "--log": log, "--params": params},
                     {"model": model_path, "views' cameras file": folder / "cameras.json"})

    # The library loads once the paths are known good: a mistyped name is refused at once.
    from statfit.core.device import resolve_device
    from statfit.geometry.support import view_support
    from statfit.io.mesh import mesh_bytes
    from statfit.io.splats import splats_bytes
    from statfit.io.views import read_views
    from statfit.model.importers.cache import open_model
    from statfit.model.params import project, vertex_fields
    from statfit.model.params_file import params_bytes
    from statfit.renderer.binding import PATTERNS
    from statfit.splat.job import fit_views, splat_records, splat_stages
    from statfit_cli.runner import finish, fit_run

    if per_triangle not in PATTERNS:
        raise StatfitError(f"--per-triangle must be one of {', '.join(map(str, PATTERNS))}, got {per_triangle}")
    stages = splat_stages(method, preset, **setting_overrides(iterations, lr, beta, power, lam, laplacian,
                                                              mode_gain))
    torch_device = resolve_device(device, "splat")
    views = read_views(folder)
    train = sum(view.split == "train" for view in views)
    if views_per_step > train:
        raise StatfitError(f"--views-per-step {views_per_step} is more than the {train} training views")
    model = open_model(model_path, k)
    header = dict(method=method, preset=preset, stages=[s.describe() for s in stages], model=model.source,
                  modes=model.num_modes, input=str(folder), views=len(views), train_views=train,
                  size=list(views[0].image.shape[:2]), per_triangle=per_triangle, views_per_step=views_per_step,
                  mask_weight=mask_weight, device=str(torch_device), threads=threads, seed=seed)
    with fit_run("splat", log, folder.name or str(folder), sum(s.iterations for s in stages), quiet, **header) as run:
        result = fit_views(model, views, stages=stages, per_triangle=per_triangle, views_per_step=views_per_step,
                           mask_weight=mask_weight, device=str(torch_device), seed=seed, on_record=run.on_record,
                           threads=threads)
    vertices = result.fit.vertices
    summary = {"input": str(folder), "output": str(out), "method": method, "iterations": result.fit.iterations,
               "final_loss": result.fit.loss, "seconds": result.fit.seconds, "threads": result.fit.threads,
               "stage_seconds": result.fit.stage_seconds, "splats": len(result.splats),
               "held_out": result.mean_scores("test"), "train": result.mean_scores("train"),
               "views": result.scores}
    projection = project(model, vertices, result.fit.transform)
    seen = [(view.camera, view.mask) for view in views if view.split == "train"]
    fields = vertex_fields(projection, *view_support(vertices, model.faces, seen))
    outputs = {out: mesh_bytes(vertices, model.faces, mesh_format(out), fields)}
    if params is not None:
        outputs[params] = params_bytes(model, projection, params)
    if splats_out is not None:
        outputs[splats_out] = splats_bytes(splat_records(result.splats, vertices), len(model.faces))
    if preview is not None:
        from statfit.splat.preview import splat_preview_png
        shown = next((view for view in views if view.split == "test"), views[0])
        outputs[preview] = splat_preview_png(shown.image, result.splats, vertices, model.faces, shown.camera,
                                             f"{shown.split} view {shown.name}")
    finish(run, summary, outputs, json_out)


def splat_render(
    splats_path: Path = typer.Argument(..., metavar="SPLATS.PLY", help="Splats from `statfit splat --splats`.",
                                       show_default=False),
    mesh_path: Path = typer.Argument(..., metavar="MESH", help="The mesh they are bound to (e.g. the fit), or any "
                                     "mesh of the same topology: the splats follow it.", show_default=False),
    camera_path: Path = typer.Option(..., "--camera", "-c", help="A camera JSON, or a views folder's cameras.json "
                                     "with --view.", show_default=False),
    view: int = typer.Option(None, help="Which camera of a cameras.json (0-based).", show_default=False),
    out: Path = typer.Option(..., "--out", "-o", help="Image to write (.png: RGBA, alpha = splat opacity; .exr).",
                             show_default=False),
) -> None:
    """Render splats bound to a mesh from a camera (a novel view, or a held-out one).

        statfit splat-render splats.ply fit.ply --camera views/cameras.json --view 3 --out novel.png
    """
    from statfit.io.image import encoded_image, image_suffix
    from statfit.io.mesh import read_mesh
    from statfit.io.files import write_atomic
    from statfit.io.splats import read_splats
    import torch

    from statfit.splat.job import render_splats, splats_from_records

    suffix = image_suffix(out)
    check_writable(out)
    refuse_overwrite({"--out": out}, {"splats": splats_path, "mesh": mesh_path, "camera file": camera_path})
    camera = _camera(camera_path, view)
    vertices, faces = read_mesh(mesh_path)
    splats = splats_from_records(read_splats(splats_path, len(faces)), torch.as_tensor(faces, dtype=torch.long))
    colour, alpha = render_splats(splats, vertices, camera)
    write_atomic(out, encoded_image(np.concatenate([colour, alpha[..., None]], axis=-1), suffix))


def _camera(path: Path, view: int | None) -> Camera:
    """The camera in ``path``: a camera JSON, or entry ``view`` of a views folder's cameras.json."""
    from statfit.structures.camera import Camera

    path = existing_file(path, "camera file")
    if path.stat().st_size > MAX_CAMERA_BYTES:
        raise StatfitError(f"{path} is larger than {MAX_CAMERA_BYTES >> 20} MiB: not a camera file")
    try:
        data = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise StatfitError(f"{path} is not valid JSON: {exc}") from None
    if isinstance(data, dict) and "views" in data:
        entries = data["views"]
        if view is None:
            raise StatfitError(f"{path} holds {len(entries)} cameras: choose one with --view")
        if not isinstance(entries, list) or not 0 <= view < len(entries) or not isinstance(entries[view], dict):
            raise StatfitError(f"{path} has no view {view} (it has {len(entries) if isinstance(entries, list) else 0})")
        return Camera.from_dict(entries[view].get("camera"))
    if view is not None:
        raise StatfitError(f"{path} is a single camera; drop --view")
    return Camera.from_dict(data)
