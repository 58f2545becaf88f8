"""``statfit synth``: test data with a known ground truth."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from statfit.errors import StatfitError
from statfit.synth.scan_options import CLUTTER_PARTS, SCAN_UNITS_PER_METRE
from statfit_cli.common import (ModelOption, QuietOption, count_bar, refuse_missing, refuse_overwrite, seed_option,
                                within)


app = typer.Typer(help="Make synthetic test data from a model, with its ground truth.", no_args_is_help=True)


SeedOption = seed_option(0, "Seed of the shape (and of the point sampling).")
SigmaOption = typer.Option(1.0, help="Coefficients ~ N(0, sigma²) in std-dev units.", callback=within(0, 100))
GtOption = typer.Option(None, help="Ground-truth mesh (template topology).", show_default=False)
DeltaOption = typer.Option(None, help="npz of off-model deltas (names (D,), deltas (N, 3, D)).", show_default=False)
DeltaNameOption = typer.Option(None, help="Which delta to add, e.g. jawOpen.", show_default=False)
DeltaWeightOption = typer.Option(1.0, help="Weight of the delta.", callback=within(-100, 100))


def check_delta_options(delta: Path | None, delta_name: str | None) -> None:
    if (delta is None) != (delta_name is None):
        raise StatfitError("--delta and --delta-name go together")


def _target(model, rng: np.random.Generator, sigma: float, delta: Path | None, delta_name: str | None,
            delta_weight: float) -> np.ndarray:
    from statfit.synth.sample import load_delta, sample_target

    offset = load_delta(str(delta), delta_name) if delta is not None else None
    return sample_target(model, rng, sigma, offset, delta_weight)


@app.command("scan")
def scan(
    out: Path = typer.Option(..., "--out", "-o", help="The scan: a point cloud, .ply or text rows x y z (.xyz, .asc, "
                             ".csv, .txt); with --realistic a mesh, .ply or .obj.", show_default=False),
    gt: Path = GtOption,
    model_path: Path = ModelOption,
    seed: int = SeedOption,
    sigma: float = SigmaOption,
    yaw: float = typer.Option(30.0, help="View direction, degrees about +y (0 looks at the +z face).",
                             callback=within(-360, 360)),
    pitch: float = typer.Option(0.0, help="View elevation, degrees.", callback=within(-89, 89)),
    points: int = typer.Option(4300, help="Number of scan points.", callback=within(10, 10_000_000)),
    noise: float = typer.Option(0.0, help="Gaussian noise, as a fraction of the shape's RMS radius.",
                               callback=within(0, 1)),
    outliers: float = typer.Option(0.0, help="Fraction of points replaced by uniform outliers.",
                                  callback=within(0, 1)),
    delta: Path = DeltaOption,
    delta_name: str = DeltaNameOption,
    delta_weight: float = DeltaWeightOption,
    realistic: bool = typer.Option(False, "--realistic", help="Scan as a range scanner would: a triangle mesh "
                                   "with clutter (hair over the scalp, neck and shoulders below), holes, surfaces "
                                   "at grazing angles lost, depth noise, in its own pose and units. --points is "
                                   "then about the points on the shape."),
    clutter: float = typer.Option(0.5, help="--realistic: clutter points per shape point (0: none).",
                                  callback=within(0, 2)),
    clutter_parts: str = typer.Option(",".join(CLUTTER_PARTS), help="--realistic: which clutter, comma-separated: "
                                      "hair (over the scalp, hiding it), neck (neck and shoulders below)."),
    holes: int = typer.Option(3, help="--realistic: disks of lost data.", callback=within(0, 100)),
    units: str = typer.Option("mm", help="--realistic: the scan's length unit (mm, cm, m or in)."),
    pose: bool = typer.Option(True, "--pose/--no-pose", help="--realistic: turn the scan by a random rotation and "
                              "offset (--no-pose: the model's frame, in --units)."),
    landmarks_out: Path = typer.Option(None, help="--realistic: the true landmarks in the scan's frame (text, "
                                       "'x y z' per model landmark).", show_default=False),
) -> None:
    """A model sample seen from one side: a partial scan plus its ground-truth mesh (in the scan's frame).

        \b
        statfit synth scan --model model.npz --seed 3 --out scan.ply --gt gt.ply
        statfit synth scan --model model.npz --seed 3 --realistic --units mm --out scan.ply --gt gt.ply
    """
    from statfit.io.files import check_writable, mesh_format, points_format, write_atomic

    if points < 10:
        raise StatfitError("--points must be at least 10")
    if not 0 <= outliers < 1:
        raise StatfitError("--outliers must lie in [0, 1)")
    if realistic and outliers > 0:
        raise StatfitError("--outliers adds loose points to a point cloud; a --realistic scan is a mesh with clutter "
                           "surfaces (--clutter) instead")
    if units not in SCAN_UNITS_PER_METRE:
        raise StatfitError(f"unknown --units {units!r}; choose one of {', '.join(SCAN_UNITS_PER_METRE)}")
    if landmarks_out is not None and not realistic:
        raise StatfitError("--landmarks-out goes with --realistic")
    parts = tuple(part.strip() for part in clutter_parts.split(",") if part.strip())
    if unknown := sorted(set(parts) - set(CLUTTER_PARTS)):
        raise StatfitError(f"unknown --clutter-parts {', '.join(unknown)}; choose from {', '.join(CLUTTER_PARTS)}")
    if not parts:
        raise StatfitError(f"--clutter-parts needs at least one of {', '.join(CLUTTER_PARTS)} (no clutter: --clutter 0)")
    for target in (out, gt, landmarks_out):
        if target is not None:
            check_writable(target)
    if gt is not None:
        mesh_format(gt)
    if realistic:
        mesh_format(out)
    else:
        points_format(out)
    check_delta_options(delta, delta_name)
    refuse_missing({"delta file": delta}, model_path)
    refuse_overwrite({"--out": out, "--gt": gt, "--landmarks-out": landmarks_out},
                     {"delta file": delta, "model": model_path})

    # The library loads once the paths are known good: a mistyped name is refused at once.
    from statfit.io.landmarks import landmarks_text
    from statfit.io.mesh import mesh_bytes, points_bytes
    from statfit.model.importers.cache import open_model
    from statfit.synth.sample import scan_from_view
    from statfit.synth.scanner import realistic_scan

    model = open_model(model_path)
    if landmarks_out is not None and model.landmarks is None:
        raise StatfitError(f"the model {model.source} has no landmarks to write")
    rng = np.random.default_rng(seed)
    shape = _target(model, rng, sigma, delta, delta_name, delta_weight)
    if not realistic:
        scan_bytes = points_bytes(scan_from_view(shape, model.faces, rng, points, yaw, pitch, noise, outliers), out)
    else:
        made = realistic_scan(shape, model.faces, rng, points, yaw, pitch, clutter, holes, noise, units, pose,
                              parts)
        scan_bytes, shape = mesh_bytes(made.vertices, made.faces, mesh_format(out)), made.truth
    write_atomic(out, scan_bytes)
    if gt is not None:
        write_atomic(gt, mesh_bytes(shape, model.faces, mesh_format(gt)))
    if landmarks_out is not None:
        write_atomic(landmarks_out, landmarks_text(shape[model.landmarks]).encode())


@app.command("normals")
def normals(
    out: Path = typer.Option(..., "--out", "-o", help="Normal map (OpenEXR, world-space normals + coverage; "
                             "the camera in its header).", show_default=False),
    camera_out: Path = typer.Option(None, help="Camera JSON.", show_default=False),
    gt: Path = GtOption,
    model_path: Path = ModelOption,
    seed: int = SeedOption,
    sigma: float = SigmaOption,
    yaw: float = typer.Option(20.0, help="View direction, degrees about +y (0 looks at the +z face).",
                             callback=within(-360, 360)),
    pitch: float = typer.Option(0.0, help="View elevation, degrees.", callback=within(-89, 89)),
    size: int = typer.Option(512, help="Image width and height, pixels.", callback=within(16, 8192)),
    fov: float = typer.Option(30.0, help="Vertical field of view, degrees.", callback=within(1, 170)),
    delta: Path = DeltaOption,
    delta_name: str = DeltaNameOption,
    delta_weight: float = DeltaWeightOption,
    shape_path: Path = typer.Option(None, "--shape", help="Render this mesh (the model's topology, e.g. from "
                                    "`statfit synth body`) instead of a model sample.", show_default=False),
) -> None:
    """A model sample (or a given --shape) seen by a pinhole camera: a normal map plus its camera and
    ground truth.

        \b
        statfit synth normals --model model.npz --seed 3 --yaw 20 --out normals.exr --camera-out camera.json --gt gt.ply
        statfit synth normals --model body.npz --shape person.ply --yaw 30 --size 768 --out body.exr --camera-out cam.json
    """
    from statfit.io.files import check_writable, mesh_format, output_suffix, write_atomic

    check_delta_options(delta, delta_name)
    output_suffix(out, (".exr",), "a normal map")
    if shape_path is not None and delta is not None:
        raise StatfitError("--shape and --delta do not go together: add the delta to the mesh itself")
    for target in (out, camera_out, gt):
        if target is not None:
            check_writable(target)
    if gt is not None:
        mesh_format(gt)
    refuse_missing({"delta file": delta, "file": shape_path}, model_path)
    refuse_overwrite({"--out": out, "--camera-out": camera_out, "--gt": gt},
                     {"delta file": delta, "shape": shape_path, "model": model_path})

    # The library loads once the paths are known good: a mistyped name is refused at once.
    from statfit.io.mesh import mesh_bytes, read_mesh
    from statfit.io.normalmap import write_camera, write_normal_map
    from statfit.model.importers.cache import open_model
    from statfit.renderer.images import render_target
    from statfit.synth.sample import camera_for_view

    model = open_model(model_path)
    if shape_path is None:
        shape = _target(model, np.random.default_rng(seed), sigma, delta, delta_name, delta_weight)
    else:
        shape, faces = read_mesh(shape_path)
        if shape.shape != model.template.shape or faces.shape != model.faces.shape or (faces != model.faces).any():
            raise StatfitError(f"{shape_path} is not in the model's topology ({model.num_vertices} vertices, "
                               f"{len(model.faces)} faces; it has {len(shape)} and {len(faces)})")
    camera = camera_for_view(shape, yaw, pitch, size, fov)
    normal_map, mask = render_target(shape, model.faces, camera)
    if not mask.any():
        raise StatfitError("the shape covers no pixel of the image")
    write_normal_map(out, normal_map, mask, camera)
    if camera_out is not None:
        write_camera(camera_out, camera)
    if gt is not None:
        write_atomic(gt, mesh_bytes(shape, model.faces, mesh_format(gt)))


@app.command("body")
def body(
    folder: Path = typer.Argument(..., help="The MakeHuman data folder, e.g. ../shared/data/makehuman.",
                                  show_default=False),
    out: Path = typer.Option(..., "--out", "-o", help="Body mesh to write (.ply or .obj), metres, the topology of "
                             "`statfit model build-makehuman`.", show_default=False),
    seed: int = seed_option(0, "Seed of the body's sliders."),
    held_out: bool = typer.Option(True, "--held-out/--train", help="held-out: a body the built model never saw "
                                  "(asymmetric, expressions, asym targets, sliders in the tails); train: a body "
                                  "from the model's own training distribution."),
    quiet: bool = QuietOption,
) -> None:
    """A random MakeHuman body, as ground truth for full-body tests (docs/bodies.md).

        \b
        statfit synth body ../shared/data/makehuman --seed 4 -o person.ply
        statfit synth normals --model body.npz --shape person.ply --yaw 30 --size 768 --out body.exr --camera-out cam.json
    """
    from statfit.io.files import check_writable, mesh_format, write_atomic
    from statfit.io.makehuman_layout import makehuman_folder

    check_writable(out)
    mesh_format(out)
    makehuman_folder(folder)

    # The library loads once the paths are known good: a mistyped name is refused at once.
    from statfit.io.mesh import mesh_bytes
    from statfit.model.importers.makehuman import read_makehuman
    from statfit.model.importers.makehuman_shapes import BodySpace

    with count_bar("reading MakeHuman's morph targets", not quiet) as advance:
        space = BodySpace(read_makehuman(folder, advance))
    weights = space.weights(np.random.default_rng(seed), 1, "held_out" if held_out else "train")
    write_atomic(out, mesh_bytes(space.shapes(weights)[0], space.data.faces, mesh_format(out)))


@app.command("views")
def views(
    out: Path = typer.Option(..., "--out", "-o", help="Folder to write: view_000.png … (RGBA: colour over black, "
                             "alpha = coverage), cameras.json (one camera per view, with its split) and gt.ply.",
                             show_default=False),
    model_path: Path = ModelOption,
    seed: int = SeedOption,
    sigma: float = SigmaOption,
    count: int = typer.Option(24, "--views", help="Number of cameras, spread over the front hemisphere (up to 70° "
                              "from the front).", callback=within(1, 1000)),
    size: int = typer.Option(256, help="Image width and height, pixels.", callback=within(16, 4096)),
    fov: float = typer.Option(30.0, help="Vertical field of view, degrees.", callback=within(1, 170)),
    test_every: int = typer.Option(6, help="Hold out every Nth view for testing (split 'test'; 0: none).",
                                   callback=within(0, 1000)),
    delta: Path = DeltaOption,
    delta_name: str = DeltaNameOption,
    delta_weight: float = DeltaWeightOption,
) -> None:
    """Photographs of a textured model sample (a generated albedo, a fixed light) from many
    cameras, with the cameras and the ground truth: the input of `statfit splat`.

        \b
        statfit synth views --model model.npz --seed 2 --views 24 --size 256 --out views/
        statfit synth views --model ict.npz --delta expressions.npz --delta-name jawOpen --out views/
    """
    check_delta_options(delta, delta_name)
    if out.exists() and not out.is_dir():
        raise StatfitError(f"{out} exists and is not a folder")
    refuse_missing({"delta file": delta}, model_path)

    # The library loads once the paths are known good: a mistyped name is refused at once.
    from statfit.io.image import write_image
    from statfit.io.mesh import mesh_bytes
    from statfit.io.files import write_atomic
    from statfit.io.views import CAMERAS_FILE, views_json
    from statfit.model.importers.cache import open_model
    from statfit.renderer.images import photograph
    from statfit.synth.views import generated_albedo, held_out_split, hemisphere_cameras

    model = open_model(model_path)
    rng = np.random.default_rng(seed)
    shape = _target(model, rng, sigma, delta, delta_name, delta_weight)
    albedo = generated_albedo(shape, rng)
    cameras = hemisphere_cameras(shape, count, size, fov)
    splits = held_out_split(count, test_every)
    if "train" not in splits:
        raise StatfitError(f"--test-every {test_every} holds out every view; keep at least one for training")
    out.mkdir(parents=True, exist_ok=True)
    entries = []
    for index, (camera, split) in enumerate(zip(cameras, splits)):
        colour, alpha = photograph(shape, model.faces, albedo, camera)
        name = f"view_{index:03d}.png"
        write_image(out / name, np.concatenate([colour, alpha[..., None]], axis=-1))
        entries.append((name, camera, split))
    write_atomic(out / "gt.ply", mesh_bytes(shape, model.faces, "ply"))
    write_atomic(out / CAMERAS_FILE, views_json(entries, gt="gt.ply"))  # last: the folder is complete
