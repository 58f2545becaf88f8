"""``statfit batch register``: every scan registered to the model."""
from __future__ import annotations

from pathlib import Path

import typer

from statfit.errors import StatfitError
from statfit_cli.batch.options import (BatchThreadsOption, ClusterOption, ForceOption, InputsArgument, JsonOption,
                                       OutDirOption, SchedulerOption, TimeoutOption, WorkersOption, planned_inputs)
from statfit_cli.common import (BetaOption, ClutterOption, DeviceOption, FallbackOption, IterationsOption, KOption,
                                LamOption, LandmarkWeightOption, LaplacianOption, LrOption, MethodOption,
                                ModeGainOption, ModelOption, PowerOption, PresetOption, QuietOption,
                                RigidModesOption, SeedOption, clutter_choice, refuse_missing, setting_overrides,
                                within)


def batch_register(
    inputs: list[str] = InputsArgument,
    out_dir: Path = OutDirOption,
    model_path: Path = ModelOption,
    k: int = KOption,
    method: str = MethodOption,
    preset: str = PresetOption,
    fallback: bool = FallbackOption,
    workers: int = WorkersOption,
    scheduler: str = SchedulerOption,
    cluster: str = ClusterOption,
    timeout: float = TimeoutOption,
    force: bool = ForceOption,
    params: bool = typer.Option(False, "--params", help="Also write each fit's code in the model beside its mesh, "
                                "<output stem>.params.json (see `statfit register --help`, docs/formats.md)."),
    align: str = typer.Option("auto", help="Pre-alignment of each scan: auto (pose, scale and units found), none, "
                              "rigid or similarity (see `statfit register --help`)."),
    region: str = typer.Option(None, "--region", metavar="<name>",
                               help="Fit only the model's region NAME (see `statfit register "
                               "--help`).", show_default=False),
    refresh: int = typer.Option(10, help="Recompute closest surface points every N iterations.",
                                callback=within(1, 100_000)),
    trim: float = typer.Option(0.05, help="Fraction of farthest scan points ignored.", callback=within(0, 0.99)),
    landmarks: str = typer.Option(None, "--landmarks", metavar="<template>",
                                  help="Each scan's own landmarks file, named by this "
                                  "template: {stem} is the scan's name without its extension, and a relative path "
                                  "lies in the scan's folder ('{stem}.pts': scans/a.ply uses scans/a.pts; "
                                  "'/data/lm/{stem}.txt'). Rows and use as for `statfit register --landmarks`. A "
                                  "scan without its file fails alone; a changed file is fitted again on a rerun.",
                                  show_default=False),
    landmark_weight: float = LandmarkWeightOption,
    clutter: str = ClutterOption,
    rigid_modes: str = RigidModesOption,
    device: str = DeviceOption,
    threads: int = BatchThreadsOption,
    together: int = typer.Option(None, "--together", help="Scans each worker registers in one program: each "
                                 "its own pose and closed-form stage, their gradient stages stepped together (one "
                                 "launch per op for all). Default: 1 on a CPU; on a GPU as many as fit in a quarter "
                                 "of its free memory, at most 64. Not the same bytes as one at a time (docs/batch.md).",
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
    """Register every scan to the model; a rerun skips the scans already done with these settings.

    Each scan gets OUT_DIR/<its path below the scans' common folder>.ply, the same mesh `statfit
    register` gives with the same options and seed. A scan that cannot be fitted is recorded as
    failed with its reason and the batch goes on. Examples:

        \b
        statfit batch register 'scans/**/*.ply' --model model.npz --out-dir fits/ --workers 2
        statfit batch register 'scans/**/*.ply' --model model.npz --out-dir fits/ --scheduler tcp://head:8786
        statfit batch register 'scans/*.ply' --out-dir fits/ --params    # fits/<scan>.params.json too
        statfit batch register 'scans/*.ply' --model flame.npz --out-dir fits/ --landmarks '{stem}.pts'
        statfit batch register 'scans/*.ply' --out-dir fits/ --device cuda --workers 4   # 4 × 64 scans at once
        statfit batch status fits/
    """
    items = planned_inputs(inputs, out_dir)
    refuse_missing({}, model_path)

    # The library loads once the paths are known good: a mistyped name is refused at once.
    from statfit.batch.fits import FitJob
    from statfit.batch.plan import check_companion_template
    from statfit.core.device import resolve_device
    from statfit.core.methods import fallback as method_fallback, resolve
    from statfit.model.cut import check_rigid_modes
    from statfit.model.statmodel import region_vertices
    from statfit.registration.many import together_for
    from statfit.registration.prealign import ALIGNMENTS
    from statfit_cli.batch.running import check_engine, create_out_dir, model_identity, run_fits

    check_engine(scheduler, cluster)
    overrides = setting_overrides(iterations, lr, beta, power, lam, laplacian, mode_gain)
    stages = resolve(method, preset, **overrides)
    refit = method_fallback(method, preset, **overrides) if fallback else None
    if align not in ALIGNMENTS:
        raise StatfitError(f"unknown alignment {align!r}; choose one of {', '.join(ALIGNMENTS)}")
    check_rigid_modes(rigid_modes)
    model_file, digest, model = model_identity(model_path, k)
    if region is not None:
        region_vertices(model, region)
    if landmarks is not None:
        check_companion_template(landmarks, "--landmarks")
        if model.landmarks is None:
            raise StatfitError(f"the model {model.source} has no landmarks, so --landmarks cannot be used "
                               "(`statfit model import --landmarks` stores them)")
    elif landmark_weight is not None:
        raise StatfitError("--landmark-weight weighs the landmarks of --landmarks; give both or neither")
    create_out_dir(out_dir)
    fit_device = resolve_device(device, "register")
    options = dict(align=align, region=region, refresh_every=refresh, trim=trim, seed=seed,
                   clutter=clutter_choice(clutter))
    if landmark_weight is not None:
        options["landmark_weight"] = landmark_weight   # only then: the settings key of batches without it stays
    if rigid_modes != "auto":
        options["rigid_modes"] = rigid_modes          # the same
    job = FitJob("register", model_file, k, stages, options, fallback=refit, threads=threads, device=str(fit_device),
                 model_digest=digest, params=params, together=together or together_for(model, fit_device),
                 landmarks=landmarks)
    run_fits(items, job, out_dir, workers, scheduler, cluster, timeout, force, quiet, json_out)
