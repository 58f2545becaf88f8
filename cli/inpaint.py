"""``statfit inpaint``: fill the holes of a texture from a PCA texture model (or by diffusion)."""
from __future__ import annotations

from pathlib import Path

import typer

from statfit.io.files import check_writable
from statfit_cli.common import (DeviceOption, JsonOption, LogOption, QuietOption, check_preview, refuse_missing,
                                refuse_overwrite)


def inpaint(
    image_path: Path = typer.Argument(..., metavar="IMAGE", help="Texture with holes: PNG or JPG (8/16-bit) or EXR "
                                      "(float); grey, RGB or RGBA.", show_default=False),
    mask: Path = typer.Option(..., "--mask", help="Mask image of the same size: white = visible, black = hole.",
                              show_default=False),
    mask_invert: bool = typer.Option(False, "--mask-invert", help="The mask marks the holes in white instead."),
    model_path: Path = typer.Option(None, "--model", "-m", help="Texture model npz from `statfit model build-texture`. "
                                    "Needed by hybrid, statistical and pca.", show_default=False),
    method: str = typer.Option(None, help="hybrid (default with --model: model modes + smooth diffusion), statistical "
                               "(model modes), pca (model coefficients only), laplacian (default without a model: "
                               "diffusion only) or none (holes keep the start colour).", show_default=False),
    out: Path = typer.Option(None, "--out", "-o", help="Filled image: .png (16-bit from a 16-bit PNG or an EXR, "
                             "else 8-bit), .jpg (8-bit) or .exr (float). Default: <image>_filled.png here.",
                             show_default=False),
    log: Path = LogOption,
    preview: Path = typer.Option(None, help="PNG: input with holes checkered | result | model-only reconstruction.",
                                 show_default=False),
    start: str = typer.Option("mean", help="Where a model method starts: mean (the model's mean texture; measured "
                              "best) or reconstruction (the model's fit to the visible pixels). Without a model: "
                              "the visible pixels' mean colour."),
    resize: bool = typer.Option(False, "--resize", help="Fit at the model's size when the image has another; the "
                                "filled holes are resampled back to the image's size."),
    charts: Path = typer.Option(None, help="UV-chart image of the same size: black = outside every chart, one colour "
                                "per chart; colour never diffuses across a chart border.", show_default=False),
    iterations: int = typer.Option(None, help="Iterations. Default: the method's (docs/method.md).",
                                   show_default=False),
    lr: float = typer.Option(None, help="Step size: UniformAdam's in colour units (images are in [0, 1]); Adam's "
                             "for pca (coefficients in standard deviations) and none.", show_default=False),
    beta: float = typer.Option(None, help="β of the statistical/hybrid filter: α = β/(1+β) of each step follows "
                               "the model's modes.", show_default=False),
    lam: float = typer.Option(None, help="λ of the grid Laplacian (laplacian, hybrid): larger spreads colour farther "
                              "and smoother.", show_default=False),
    device: str = DeviceOption,
    quiet: bool = QuietOption,
    json_out: bool = JsonOption,
) -> None:
    """Texture inpainting: fit every pixel to the visible ones (L1) through a gradient filter, so the
    holes are filled with what the filter spreads into them (the model's modes and/or diffusion).

    Visible pixels keep their input values. Examples:

        statfit inpaint face.png --mask holes.png --model tex.npz --out filled.png --preview preview.png

        statfit inpaint face.png --mask holes.png --method laplacian --lam 99 --out blurry.png
    """
    from statfit.io.image import image_suffix

    method = method or ("hybrid" if model_path is not None else "laplacian")
    out = out or Path(f"{image_path.stem}_filled.png")
    image_suffix(out)
    check_preview(preview)
    for target in (out, log, preview):
        if target is not None:
            check_writable(target)
    refuse_missing({"image": image_path, "mask": mask, "chart image": charts, "texture model file": model_path})
    refuse_overwrite({"--out": out, "--log": log, "--preview": preview},
                     {"image": image_path, "mask": mask, "chart image": charts, "texture model file": model_path})

    # The library loads once the paths are known good: a mistyped name is refused at once.
    from statfit.core.device import resolve_device
    from statfit.io.image import encoded_image, read_charts, read_image, read_mask, sample_bits
    from statfit.texture.inpaint import inpaint as fill, inpaint_settings
    from statfit.texture.model import load_texture_model
    from statfit_cli.runner import finish, fit_run

    settings = inpaint_settings(method, iterations, lr, beta, lam)
    torch_device = resolve_device(device)
    image = read_image(image_path)
    bits = 16 if sample_bits(image_path) > 8 else 8     # a PNG out keeps a deeper input's precision
    visible = read_mask(mask) != mask_invert
    labels = read_charts(charts) if charts is not None else None
    model = load_texture_model(model_path) if model_path is not None else None
    header = dict(method=method, settings=settings.describe(), input=str(image_path), mask=str(mask),
                  mask_invert=mask_invert, model=str(model_path) if model_path else None,
                  modes=model.num_modes if model else 0, size=list(image.shape), start=start, resize=resize,
                  charts=str(charts) if charts else None, visible_pixels=int(visible.sum()), device=str(torch_device))
    with fit_run("inpaint", log, image_path.name, settings.iterations, quiet, **header) as run:
        result = fill(image, visible, method, model, settings=settings, start=start, charts=labels, resize=resize,
                      device=torch_device, on_record=run.on_record)
    summary = {"input": str(image_path), "output": str(out), "method": method, "iterations": settings.iterations,
               "width": image.shape[1], "height": image.shape[0], "channels": image.shape[2],
               "hole_pixels": int((~visible).sum()), "final_loss": result.loss, "seconds": result.seconds}
    outputs = {out: encoded_image(result.result, image_suffix(out), bits)}
    if preview is not None:
        from statfit.texture.preview import preview_png
        outputs[preview] = preview_png(image, visible, result.result, result.model_only)
    finish(run, summary, outputs, json_out)
