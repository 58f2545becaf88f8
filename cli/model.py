"""``statfit model``: import, build, inspect and sample statistical models."""
from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from statfit.errors import StatfitError
if TYPE_CHECKING:
    from statfit.model.statmodel import StatModel
from statfit_cli.common import (QuietOption, SeedOption, count_bar, printed_warnings, refuse_missing,
                                refuse_overwrite, seed_option, stage_line, within)


app = typer.Typer(help="Import, build, inspect and sample statistical models.", no_args_is_help=True)

ANY_MODEL = ("a model npz, a FLAME/SMPL-X/SMPL .pkl or .npz, an ICT-FaceKit FaceXModel folder or a "
             "Basel Face Model 2017 .h5")
EXPLAINED_AT = (1, 5, 10, 20, 50, 100, 200, 300)


def _explained(cumulative: np.ndarray, with_last: bool) -> dict[str, float]:
    """Cumulative variance explained at a few k (and at the last mode with ``with_last``)."""
    shown = [k for k in EXPLAINED_AT if k <= len(cumulative)] + [len(cumulative)] * with_last
    return {str(k): float(cumulative[k - 1]) for k in shown}


def _check_output(out: Path, *inputs: Path) -> None:
    from statfit.io.files import check_writable, output_suffix

    output_suffix(out, (".npz",), "a model")
    check_writable(out)
    if any(out.resolve() == p.resolve() for p in inputs):
        raise StatfitError(f"the output {out} would overwrite an input; choose another path")


def _summary(model: StatModel) -> str:
    return f"{model.num_vertices} vertices, {len(model.faces)} faces, {model.num_modes} modes" + \
        (f", {model.landmarks.size} landmarks" if model.landmarks is not None else "") + \
        (f", regions {'+'.join(model.regions)}" if model.regions else "")


@app.command("import")
def import_(
    source: Path = typer.Argument(..., help=f"The model to convert: {ANY_MODEL}.", show_default=False),
    out: Path = typer.Option(..., "--out", "-o", help="Model npz to write.", show_default=False),
    k: int = typer.Option(None, "--k", help="Keep the first K identity directions (FLAME/SMPL-X: of 300; "
                          "ICT: identity meshes; BFM: principal components). Default: all.", show_default=False),
    expressions: bool = typer.Option(False, "--expressions", help="Also keep the expression directions "
                                     "(FLAME, SMPL-X: shapedirs after the 300 identity ones; BFM: the expression model)."),
    region: str = typer.Option(None, "--region", metavar="<name>",
                               help="ICT-FaceKit only: geometries to keep, joined by '+' "
                               "(face, head, mouth_socket, eye_socket_left, ..., teeth, eyeball_left, ...). "
                               "Default: face+head. Each is stored as region_<name>.", show_default=False),
    masks: Path = typer.Option(None, "--masks", help="Named vertex masks to store as regions (region_<name>), "
                               "e.g. FLAME_masks.pkl (face, forehead, eye_region, lips, scalp, neck, ...): a pickle "
                               "or npz of name → vertex indices.", show_default=False),
    landmarks: Path = typer.Option(None, "--landmarks", help="Text file of landmark vertex indices (in the "
                                   "imported mesh's numbering), stored as the model's landmarks for "
                                   "register --landmarks.", show_default=False),
) -> None:
    """Convert a model from its original format to statfit's npz (v_template, faces, shapedirs scaled by
    the standard deviations, region_<name>). No chumpy is needed for FLAME pickles, and nothing in a
    pickle is executed.

        \b
        statfit model import generic_model.pkl -o flame.npz --masks FLAME_masks.pkl
        statfit model import SMPLX_NEUTRAL.npz -o smplx.npz --expressions
        statfit model import ICT-FaceKit/FaceXModel -o ict.npz --region face+head
        statfit model import model2017-1_bfm_nomouth.h5 -o bfm.npz --k 100

    Any command's --model also takes the original file directly (imported once, cached).
    """
    _check_output(out, source, *[p for p in (masks, landmarks) if p is not None])
    refuse_missing({"mask file": masks, "landmark file": landmarks}, source)

    # The library loads once the paths are known good: a mistyped name is refused at once.
    from statfit.model.importers import import_model
    from statfit.model.statmodel import save_model

    model = import_model(source, k=k, expressions=expressions, region=region, masks=masks, landmarks=landmarks)
    save_model(model, out)
    print(f"{out}: {_summary(model)} (from {model.source})")


@app.command("build")
def build(
    meshes: list[Path] = typer.Argument(..., help="Registered meshes: same vertex count, faces and vertex "
                                        "order (PLY, OBJ, STL, OFF).", show_default=False),
    out: Path = typer.Option(..., "--out", "-o", help="Model npz to write.", show_default=False),
    k: int = typer.Option(None, "--k", help="Principal components to keep. Default: all (meshes − 1).",
                          show_default=False),
    seed: int = seed_option(0, "Seed of the randomised SVD (used for many large meshes)."),
    json_out: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    """Build a PCA model from meshes in correspondence (e.g. registrations of many scans):
    template = mean mesh, shapedirs = principal directions × standard deviations.

        statfit model build registered/*.ply -o mine.npz --k 50
    """
    _check_output(out, *meshes)
    refuse_missing({"file": list(meshes)})

    # The library loads once the paths are known good: a mistyped name is refused at once.
    from statfit.model.build import build_model_from_files
    from statfit.model.statmodel import save_model

    with printed_warnings():
        built = build_model_from_files(meshes, k, seed=seed)
    save_model(built.model, out)
    report = {"output": str(out), "meshes": len(meshes), "vertices": built.model.num_vertices,
              "modes": built.model.num_modes, "variance_explained": _explained(built.variance_explained, True)}
    if json_out:
        print(json.dumps(report))
        return
    shares = ", ".join(f"{key}: {value:.1%}" for key, value in report["variance_explained"].items())
    print(f"{out}: {_summary(built.model)} from {len(meshes)} meshes; variance explained by the first k modes: {shares}")


@app.command("build-makehuman")
def build_makehuman(
    folder: Path = typer.Argument(..., help="The MakeHuman data folder (3dobjs/base.obj.gz, targets/, "
                                  "mesh_metadata/), e.g. ../shared/data/makehuman.", show_default=False),
    out: Path = typer.Option(..., "--out", "-o", help="Model npz to write (shapedirs as float32).",
                             show_default=False),
    k: int = typer.Option(300, "--k", help="Principal components to keep.", callback=within(1, 100_000)),
    samples: int = typer.Option(5000, help="Random bodies the PCA learns from.", callback=within(2, 1_000_000)),
    seed: int = seed_option(0, "Seed of the random bodies: the same seed builds the same model."),
    json_out: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
    quiet: bool = QuietOption,
) -> None:
    """Build a full-body PCA model from the open MakeHuman base mesh and morph targets (CC0): the skin
    (13,380 vertices, metres, file order), learnt from random bodies (global sliders gender, age,
    muscle, weight, height, proportions, race as MakeHuman blends them; local sliders for every body
    part, symmetric). Regions head, arms, legs, torso, left, right. The asym and expression targets
    and asymmetric bodies are kept out, for held-out tests (statfit synth body). docs/bodies.md.

        statfit model build-makehuman ../shared/data/makehuman -o body.npz --k 300 --samples 5000 --seed 0
    """
    from statfit.io.makehuman_layout import makehuman_folder

    _check_output(out)
    makehuman_folder(folder)

    from statfit.model.importers.makehuman import read_makehuman
    from statfit.model.importers.makehuman_shapes import body_regions, BodySpace, build_body_model
    from statfit.model.statmodel import save_model

    with count_bar("reading MakeHuman's morph targets", not quiet) as advance:
        space = BodySpace(read_makehuman(folder, advance))
    with stage_line(f"learning {k} modes from {samples:,} random bodies", not quiet):
        built = build_body_model(space, k, samples, seed, body_regions(space))
    save_model(built.model, out, np.float32)
    report = {"output": str(out), "samples": samples, "vertices": built.model.num_vertices,
              "modes": built.model.num_modes, "variance_explained": _explained(built.variance_explained, True)}
    if json_out:
        print(json.dumps(report))
        return
    shares = ", ".join(f"{key}: {value:.4%}" for key, value in report["variance_explained"].items())
    print(f"{out}: {_summary(built.model)} from {samples} random bodies; variance explained by the first k "
          f"modes: {shares}")


@app.command("cut")
def cut(
    model_path: Path = typer.Argument(..., help=f"The model: {ANY_MODEL}.", show_default=False),
    out: Path = typer.Option(..., "--out", "-o", help="Model npz to write.", show_default=False),
    region: str = typer.Option(None, "--region", metavar="<name>",
                               help="Keep only this region of the model (see `statfit model "
                               "info`), e.g. face: a face-mask model cut from a head.", show_default=False),
    vertices: int = typer.Option(None, "--vertices", help="Decimate to about this many vertices (each kept vertex "
                                 "keeps its place and modes; landmarks move to the nearest kept vertex).",
                                 show_default=False, callback=within(4, 10_000_000)),
    scale: float = typer.Option(1.0, "--scale", help="Multiply lengths by this factor (10: cm → mm).",
                                callback=within(0, 1e6, above=True)),
    rigid_free: bool = typer.Option(False, "--without-rigid-motion",
                                    help="Take the modes' rigid motion out (after the cut). For a part whose modes "
                                    "mostly move it, as a head cut from a body model rises with the body's height "
                                    "(`model info`: rigid motion); register, render and batch do it by themselves "
                                    "above 90% (--rigid-modes; docs/studies.md §43–§44)."),
    json_out: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    """Another model made from MODEL: a region of it, fewer vertices, other units, its modes without
    rigid motion. Its modes are re-derived from the original's on the kept vertices, so it describes
    the same people.

        statfit model cut ict.npz --region face --vertices 3000 --scale 10 -o face_mask_mm.npz
        statfit model cut body.npz --region head --without-rigid-motion -o head.npz
    """
    _check_output(out, model_path)
    refuse_missing({}, model_path)

    # The library loads once the paths are known good: a mistyped name is refused at once.
    from statfit.model.cut import decimated, region_part, rescaled, without_rigid_motion
    from statfit.model.importers.cache import open_model
    from statfit.model.statmodel import save_model, units_guess

    model = open_model(model_path)
    with printed_warnings():
        if region is not None:
            model = region_part(model, region)
        if vertices is not None:
            model = decimated(model, vertices)
    model = rescaled(model, scale)
    if rigid_free:
        model = without_rigid_motion(model)
    save_model(model, out)
    report = {"output": str(out), "vertices": model.num_vertices, "faces": int(len(model.faces)),
              "modes": model.num_modes, "landmarks": 0 if model.landmarks is None else int(model.landmarks.size),
              "regions": sorted(model.regions), "units_guess": units_guess(model.surface_template)}
    if json_out:
        print(json.dumps(report))
        return
    print(f"{out}: {_summary(model)}, units {report['units_guess']}")


@app.command("sample")
def sample(
    ctx: typer.Context,
    model_path: Path = typer.Argument(None, help=f"The model: {ANY_MODEL}. Default: the embedded synthetic head.",
                                      show_default=False),
    out: str = typer.Option(..., "--out", "-o", metavar="<path>",
                            help="Mesh to write (.ply or .obj; '-' for PLY on stdout).",
                            show_default=False),
    sigma: float = typer.Option(1.0, help="Coefficients ~ N(0, sigma²) in standard deviations; 0 gives the template.",
                               callback=within(0, 100)),
    seed: int = SeedOption,
    params: Path = typer.Option(None, "--params", help="Instead of a random shape (no --sigma, --seed), the "
                                "shape a params file codes (`register/render/splat --params`): the model at its "
                                "coefficients, posed by its similarity, in the data's frame. The model (and --k) "
                                "must be the fit's.",
                                show_default=False),
    k: int = typer.Option(None, "--k", help="Use only the first K modes (as the fit did).", show_default=False),
) -> None:
    """A random shape from the model, in the model's topology and units; or, with --params, the
    shape a fit's params file codes.

        \b
        statfit model sample flame.npz --sigma 2 --seed 1 -o sample.ply
        statfit model sample flame.npz --params fit.params.json -o projection.ply
    """
    from statfit.io.files import check_writable, mesh_format, write_atomic

    if not np.isfinite(sigma) or sigma < 0:
        raise StatfitError("--sigma must be a finite number ≥ 0")
    # Typed on the command line (or from the environment): not the default. By name: typer vendors click.
    given = [f"--{name}" for name in ("sigma", "seed") if ctx.get_parameter_source(name).name != "DEFAULT"]
    if params is not None and given:
        raise StatfitError(f"--params gives the shape; {' and '.join(given)} would not change it: leave "
                           f"{'them' if len(given) > 1 else 'it'} out")
    check_writable(out)
    mesh_format(out)
    refuse_missing({"params file": params}, model_path)
    refuse_overwrite({"--out": out}, {"params file": params, "model": model_path})

    # The library loads once the paths are known good: a mistyped name is refused at once.
    from statfit.io.mesh import mesh_bytes
    from statfit.model.importers.cache import open_model
    from statfit.model.params import posed_shape
    from statfit.model.params_file import read_params

    model = open_model(model_path, k)
    if params is not None:
        vertices = posed_shape(model, read_params(params, model))
    else:
        vertices = model.sample(np.random.default_rng(seed), sigma)
    write_atomic(out, mesh_bytes(vertices, model.faces, mesh_format(out)))


@app.command("info")
def info(
    model_path: Path = typer.Argument(None, help=f"The model: {ANY_MODEL}. Default: the embedded synthetic head.",
                                      show_default=False),
    json_out: bool = typer.Option(False, "--json", help="Print as JSON."),
) -> None:
    """Vertices, faces, modes, variance explained, bounding box and a guess of the units of a model."""
    refuse_missing({}, model_path)

    # The library loads once the paths are known good: a mistyped name is refused at once.
    from statfit.model.cut import MOSTLY_RIGID, NO_RIGID_MOTION, rigid_motion_share
    from statfit.model.importers import unread_npz_keys
    from statfit.model.importers.cache import open_model
    from statfit.model.statmodel import units_guess

    model = open_model(model_path)
    extent = np.ptp(model.template, axis=0)
    report = {
        "model": model.source, "vertices": model.num_vertices, "faces": int(len(model.faces)),
        "modes": model.num_modes, "std_first": float(model.std[0]), "std_last": float(model.std[-1]),
        "variance_explained": _explained(model.variance_explained(), False),
        "rigid_motion_share": rigid_motion_share(model),
        "bbox_extent": extent.tolist(), "units_guess": units_guess(model.surface_template),
        "landmarks": 0 if model.landmarks is None else int(model.landmarks.size),
        "regions": {name: int(idx.size) for name, idx in model.regions.items()},
        "unread_keys": unread_npz_keys(model_path) if model_path is not None else [],
    }
    if json_out:
        print(json.dumps(report))
        return
    table = Table(title=str(model.source), show_header=False)
    table.add_column("key")
    table.add_column("value")
    for key, value in report.items():
        if key == "model":
            continue
        if isinstance(value, dict):
            value = ", ".join(f"{k}: {v:.4g}" if isinstance(v, float) else f"{k}: {v}" for k, v in value.items()) or "-"
        elif key == "unread_keys":
            value = ", ".join(value) or "-"
        elif isinstance(value, list):
            value = " × ".join(f"{v:.4g}" for v in value)
        elif key == "rigid_motion_share":
            if value < NO_RIGID_MOTION:
                value = f"{value:.1%} of the modes' variance (none to drop: register's closed form moves the pose)"
            else:
                fitted = "fits drop it" if value > MOSTLY_RIGID else "fits keep it"
                value = f"{value:.1%} of the modes' variance ({fitted}: --rigid-modes auto)"
        elif isinstance(value, float):
            value = f"{value:.4g}"
        table.add_row(key.replace("_", " "), str(value))
    Console().print(table)
