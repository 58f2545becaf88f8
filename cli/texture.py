"""``statfit model build-texture``: a PCA texture model from a set of images."""
from __future__ import annotations

import glob
import json
import sys
import time
from pathlib import Path

import typer
from rich.progress import track

from statfit.errors import StatfitError
from statfit_cli.common import QuietOption, printed_warnings, seed_option, stderr, within

PCA_KINDS = {"auto": None, "exact": False, "randomized": True}


def image_files(inputs: list[str]) -> list[Path]:
    """Image files named by ``inputs``: files, folders (their images, sorted) and glob patterns."""
    from statfit.io.image import IMAGE_SUFFIXES

    files: list[Path] = []
    for item in inputs:
        path = Path(item)
        if path.is_dir():
            images = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
            if not images:
                raise StatfitError(f"no image in the folder {path} (looked for {', '.join(sorted(IMAGE_SUFFIXES))})")
            files += images
        elif path.exists() or not glob.has_magic(item):
            files.append(path)
        else:
            matches = sorted(glob.glob(item))
            if not matches:
                raise StatfitError(f"no file matches {item}")
            files += [Path(m) for m in matches]
    return files


MAX_SIDE = 8192


def parse_size(size: str) -> tuple[int, int]:
    """``256`` → (256, 256); ``HxW`` → (H, W)."""
    parts = size.lower().split("x")
    try:
        height, width = (int(parts[0]), int(parts[0])) if len(parts) == 1 else (int(parts[0]), int(parts[1]))
    except ValueError:
        raise StatfitError(f"--size must be N or HEIGHTxWIDTH, got {size!r}") from None
    if len(parts) > 2 or not (2 <= height <= MAX_SIDE and 2 <= width <= MAX_SIDE):
        raise StatfitError(f"--size must be N or HEIGHTxWIDTH with sides from 2 to {MAX_SIDE}, got {size!r}")
    return height, width


def build_texture(
    inputs: list[str] = typer.Argument(..., metavar="TEXTURES...", help="Images (PNG, JPG, EXR), folders of images, "
                                       "or quoted glob patterns.", show_default=False),
    out: Path = typer.Option(..., "--out", "-o", help="Model npz to write.", show_default=False),
    k: int = typer.Option(200, "--k", help="Modes to keep (at most the number of samples − 1)."),
    size: str = typer.Option(None, help="Model resolution: N (square) or HEIGHTxWIDTH; every image is resampled "
                             "to it. Default: the first image's own size.", show_default=False),
    jitter: int = typer.Option(0, help="Add N colour-jittered copies of each texture (brightness, contrast and a "
                               "per-channel gain), so the model learns colour variation: 176 textures with "
                               "--jitter 9 give 1,760 samples.", callback=within(0, 1000)),
    pca: str = typer.Option("auto", help="auto (randomised for large problems), exact or randomized."),
    seed: int = seed_option(0, "Seed of the jitter and the randomised PCA."),
    quiet: bool = QuietOption,
    json_out: bool = typer.Option(False, "--json", help="Print a summary as JSON on stdout."),
) -> None:
    """Build a PCA texture model from images: resample each to --size, add colour-jittered copies,
    keep the first K principal components.

    The npz follows the model contract with a texture as a template of H·W "vertices" of C
    channels (docs/formats.md). Example:

        statfit model build-texture textures/*.png -o tex.npz --k 200 --size 256 --jitter 9
    """
    from statfit.io.image import read_image
    from statfit.io.files import check_writable, output_suffix
    from statfit.texture.model import build_texture_model

    if pca not in PCA_KINDS:
        raise StatfitError(f"unknown --pca {pca!r}; choose auto, exact or randomized")
    if k < 1:
        raise StatfitError("--k must be at least 1")
    shape = parse_size(size) if size is not None else None
    output_suffix(out, (".npz",), "a texture model")
    check_writable(out)
    files = image_files(inputs)
    if shape is None:
        shape = read_image(files[0]).shape[:2]
    started = time.perf_counter()
    show = not quiet and sys.stderr.isatty()
    images = ((str(f), read_image(f)) for f in files)
    if show:
        images = track(images, description="reading", total=len(files), console=stderr, transient=True)
    with printed_warnings():
        model = build_texture_model(images, shape, k, jitter=jitter, seed=seed, randomized=PCA_KINDS[pca])
    model.save(out)
    summary = {"output": str(out), "textures": len(files), "samples": len(files) * (1 + jitter), "height": shape[0],
               "width": shape[1], "channels": model.channels, "modes": model.num_modes,
               "std_first": float(model.std[0]), "std_last": float(model.std[-1]),
               "seconds": time.perf_counter() - started}
    if json_out:
        print(json.dumps(summary))
