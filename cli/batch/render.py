"""``statfit batch render``: the model fitted to every normal map."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer

from statfit.errors import StatfitError
from statfit.objectives.weights import SILHOUETTE_WEIGHT
if TYPE_CHECKING:
    from statfit.batch.plan import Item
from statfit_cli.batch.options import (BatchThreadsOption, ClusterOption, ForceOption, InputsArgument, JsonOption,
                                       OutDirOption, SchedulerOption, TimeoutOption, WorkersOption, planned_inputs)
from statfit_cli.common import (BetaOption, DeviceOption, IterationsOption, KOption, LamOption, LaplacianOption,
                                LrOption, MethodOption, ModeGainOption, ModelOption, PowerOption, PresetOption,
                                QuietOption, RigidModesOption, SeedOption, SilhouetteOption, refuse_missing,
                                setting_overrides, within)


def batch_render(
    inputs: list[str] = InputsArgument,
    out_dir: Path = OutDirOption,
    camera_path: str = typer.Option(None, "--camera", "-c", metavar="<path|template>",
                                    help="One camera JSON for every map, or each map's own "
                                    "named by a template: {stem} is the map's name without its extension, and a "
                                    "relative path lies in the map's folder ('{stem}.json': maps/a.png uses "
                                    "maps/a.json). Default: each map's own camera, from its EXR header.",
                                    show_default=False),
    camera_from_header: bool = typer.Option(False, "--camera-from-header", help="Each map's camera from its EXR "
                                            "header (the default; say it to make a script explicit)."),
    model_path: Path = ModelOption,
    k: int = KOption,
    method: str = MethodOption,
    preset: str = PresetOption,
    workers: int = WorkersOption,
    scheduler: str = SchedulerOption,
    cluster: str = ClusterOption,
    timeout: float = TimeoutOption,
    force: bool = ForceOption,
    params: bool = typer.Option(False, "--params", help="Also write each fit's code in the model beside its mesh, "
                                "<output stem>.params.json (see `statfit register --help`, docs/formats.md)."),
    align: str = typer.Option("rigid", help="Initial alignment: rigid, similarity or none (see `statfit render "
                              "--help`)."),
    normal_space: str = typer.Option("world", help="Frame of the maps' normals: world or camera."),
    normal_convention: str = typer.Option("opencv", help="Axes of camera-space normals: opencv or opengl."),
    silhouette_weight: float = typer.Option(SILHOUETTE_WEIGHT, help="Weight of the silhouette term (0: off).",
                                            callback=within(0, 1e6)),
    silhouette: str = SilhouetteOption,
    rigid_modes: str = RigidModesOption,
    region: str = typer.Option(None, "--region", metavar="<name>",
                               help="Fit only the model's region NAME.", show_default=False),
    device: str = DeviceOption,
    threads: int = BatchThreadsOption,
    together: int = typer.Option(None, "--together", help="Maps each worker fits in one program: each its own "
                                 "alignment, their fits stepped together (one renderer for all, one launch per op). "
                                 "Default: 1 on a CPU; on a GPU as many as fit in a quarter of its free memory, at "
                                 "most 64. Not the same bytes as one at a time (docs/batch.md).",
                                 show_default=False, callback=within(1, 4096)),
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
    """Fit the model to every normal map (inverse rendering); a rerun skips the maps already done.

    Example:

        \b
        statfit batch render 'maps/*.exr' --camera-from-header --model model.npz --out-dir fits/ --workers 2
        statfit batch render 'maps/*.exr' --out-dir fits/ --params    # fits/<map>.params.json too
        statfit batch render 'maps/*.exr' --out-dir fits/ --device cuda --workers 4   # many maps at once a worker
        statfit batch render 'maps/*.png' --camera '{stem}.json' --out-dir fits/   # each map's camera beside it
    """
    from statfit.batch.plan import STEM

    items = planned_inputs(inputs, out_dir)
    per_map = camera_path is not None and STEM in camera_path
    refuse_missing({"camera file": None if per_map else camera_path}, model_path)

    # The library loads once the paths are known good: a mistyped name is refused at once.
    from statfit.batch.fits import FitJob
    from statfit.core.device import resolve_device
    from statfit.io.normalmap import read_camera
    from statfit.model.cut import check_rigid_modes
    from statfit.model.statmodel import region_vertices
    from statfit.render.framing import NORMAL_CONVENTIONS, NORMAL_SPACES
    from statfit.render.job import ALIGNMENTS, render_stages, silhouette_sides
    from statfit.render.many import together_for
    from statfit_cli.batch.running import check_engine, create_out_dir, model_identity, run_fits

    check_engine(scheduler, cluster)
    if camera_path is not None and camera_from_header:
        raise StatfitError("use either --camera FILE or --camera-from-header, not both")
    stages = render_stages(method, preset, region,
                           **setting_overrides(iterations, lr, beta, power, lam, laplacian, mode_gain))
    for value, allowed, name in ((align, ALIGNMENTS, "alignment"), (normal_space, NORMAL_SPACES, "normal space"),
                                 (normal_convention, NORMAL_CONVENTIONS, "normal convention")):
        if value not in allowed:
            raise StatfitError(f"unknown {name} {value!r}; choose one of {', '.join(allowed)}")
    check_rigid_modes(rigid_modes)
    camera = None
    if per_map:
        camera = camera_path                # each map's own, read with the map; its bytes in the map's digest
    elif camera_path is not None:
        read_camera(camera_path)  # checked once, here
        camera = str(Path(camera_path).resolve())
    model_file, digest, model = model_identity(model_path, k)
    sides = silhouette_sides(silhouette, model)       # checked before any folder is made
    if region is not None:
        region_vertices(model, region)
    create_out_dir(out_dir)
    fit_device = resolve_device(device, "render")
    if together is None:
        together = together_for(model, _map_pixels(items), fit_device) if fit_device.type == "cuda" else 1
    job = FitJob("render", model_file, k, stages,
                 dict(camera=camera, align=align, normal_space=normal_space, normal_convention=normal_convention,
                      silhouette_weight=silhouette_weight, silhouette=sides, region=region, seed=seed)
                 | ({} if rigid_modes == "auto" else {"rigid_modes": rigid_modes}),
                 threads=threads, device=str(fit_device), model_digest=digest, params=params, together=together)
    run_fits(items, job, out_dir, workers, scheduler, cluster, timeout, force, quiet, json_out)


# The pixels assumed of a batch's maps when none of the first few can be read (a 1024² map).
ASSUMED_PIXELS = 1024 * 1024


def _map_pixels(items: list[Item]) -> int:
    """The pixel count of the first readable map of the first few ``items`` (a batch's maps are
    usually of one size), else :data:`ASSUMED_PIXELS`."""
    from statfit.io.normalmap import read_normal_map

    for item in items[:8]:
        try:
            return int(read_normal_map(item.source).mask.size)
        except Exception:  # noqa: BLE001 - an unreadable map fails in its own fit; here it says nothing
            continue
    return ASSUMED_PIXELS
