"""``statfit batch``: fit a dataset — many scans or normal maps, resumable, on a process pool or a
Dask cluster — and report where a batch stands."""
from __future__ import annotations

import dataclasses
import json
import signal
import statistics
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from statfit.batch.engines import DaskPool, Engine, LocalPool
from statfit.batch.fits import FitJob
from statfit.batch.manifest import MANIFEST_NAME, batch_status
from statfit.batch.plan import Item, expand_inputs, plan_outputs
from statfit.batch.run import BatchReport, run_batch
from statfit.errors import StatfitError
from statfit.model.importers.cache import content_key, open_model
from statfit.render.job import ALIGNMENTS, NORMAL_CONVENTIONS, NORMAL_SPACES, render_stages
from statfit.registration.job import ALIGNMENTS as SCAN_ALIGNMENTS
from statfit.io.normalmap import read_camera
from statfit.core.methods import resolve
from statfit.model.statmodel import StatModel, region_vertices
from statfit.objectives.normals import SILHOUETTE_WEIGHT
from statfit.core.device import resolve_device
from statfit.core.threads import available_cores
from statfit_cli.common import (BetaOption, ClutterOption, DeviceOption, IterationsOption, KOption, LamOption,
                                LaplacianOption, LrOption, MethodOption, ModeGainOption, ModelOption, PowerOption,
                                PresetOption, QuietOption, SeedOption, PROGRESS_LINE_SECONDS, clutter_choice,
                                setting_overrides, stderr, within)

app = typer.Typer(help="Fit datasets: many inputs, resumable, on local processes or a Dask cluster. "
                  "Exit codes: 0 every input done, 1 some failed (see `statfit batch status`), 2 the batch "
                  "could not start (bad options, no inputs), 130 interrupted (rerun the same command to resume).",
                  no_args_is_help=True)

EXIT_FAILED = 1
EXIT_INTERRUPTED = 130

InputsArgument = typer.Argument(..., metavar="INPUTS...", help="Files or quoted globs ('scans/**/*.ply': ** spans "
                                "sub-folders, mirrored under --out-dir). Files inside --out-dir are left out.",
                                show_default=False)
OutDirOption = typer.Option(..., "--out-dir", "-o", help="Output folder (created): one <input>.ply per input and "
                            f"{MANIFEST_NAME}, the record that makes a rerun skip what is done.", show_default=False)
WorkersOption = typer.Option(None, help="Fits at once on this machine (one process each). Default: the cores "
                             "available.", show_default=False, callback=within(1, 1024))
SchedulerOption = typer.Option(None, help="Run on the Dask cluster whose scheduler is at ADDRESS (e.g. "
                               "tcp://head:8786; needs statfit[dask]; workers must see the inputs and the model "
                               "at the same paths).", show_default=False)
ClusterOption = typer.Option(None, help="'local': a Dask LocalCluster of --workers processes on this machine.",
                             show_default=False)
TimeoutOption = typer.Option(None, help="Seconds one fit may take; past it the fit is failed and its worker "
                             "replaced. Default: no limit.", show_default=False, callback=within(0, 1e7, above=True))
ForceOption = typer.Option(False, "--force", help="Redo every input, even those done with the same settings.")
JsonOption = typer.Option(False, "--json", help="Print each input's manifest line, then the batch summary, as JSON "
                          "lines on stdout.")
BatchThreadsOption = typer.Option(None, help="CPU threads per fit. Default: 1 for head-sized models, else the "
                                  "cores shared among the workers.", show_default=False, callback=within(1, 256))


def _check_engine(scheduler: str | None, cluster: str | None) -> None:
    if scheduler is not None and cluster is not None:
        raise StatfitError("use either --scheduler ADDRESS or --cluster local, not both")
    if cluster is not None and cluster != "local":
        raise StatfitError(f"--cluster takes 'local' (a Dask LocalCluster), got {cluster!r}")


def _engine(workers: int | None, scheduler: str | None, cluster: str | None) -> tuple[Engine, int | None]:
    """The engine and the thread cap of each of its fits."""
    count = workers or available_cores()
    share = max(1, available_cores() // count)
    if scheduler is not None:
        return DaskPool(scheduler, count), None
    if cluster is not None:
        return DaskPool("local", count, share), share
    return LocalPool(count, share), share


def _prepared(inputs: list[str], out_dir: Path) -> list[Item]:
    """Every input with its output under ``out_dir`` (created), refused before any work if two
    would clash."""
    if out_dir.exists() and not out_dir.is_dir():
        raise StatfitError(f"--out-dir is a file: {out_dir}")
    items = plan_outputs(expand_inputs(inputs, exclude=out_dir), out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StatfitError(f"cannot create {out_dir}: {exc.strerror}") from None
    return items


def _model_identity(model_path: Path | None, k: int | None) -> tuple[str | None, str, StatModel]:
    """The model's path for the workers, its content digest (for the settings key), and the model,
    opened here once so that a bad model stops the batch before it starts."""
    model = open_model(model_path, k)
    digest = content_key(model_path, {}) if model_path is not None else model.source
    return (str(model_path.resolve()) if model_path is not None else None), digest, model


@contextmanager
def _terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM (a scheduler ending the job) stops the batch as Ctrl-C does."""
    def interrupt(signum, frame):
        raise KeyboardInterrupt
    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class _Progress:
    """One bar for the batch (done, failed, rate, ETA) on a terminal; otherwise a line every few seconds."""

    def __init__(self, quiet: bool, json_out: bool):
        self.quiet, self.json_out = quiet, json_out
        self.done = self.failed = self.total = 0
        self.started = self.last = time.perf_counter()
        self._bar = None

    def start(self, to_fit: int, skipped: int) -> None:
        self.total = to_fit
        if not self.quiet:
            stderr.print(f"statfit: batch: {to_fit} to fit, {skipped} already done", highlight=False)
        if not self.quiet and sys.stderr.isatty() and to_fit:
            columns = (TextColumn("batch"), BarColumn(), MofNCompleteColumn(), TextColumn("failed {task.fields[failed]}"),
                       TextColumn("{task.fields[rate]}"), TimeElapsedColumn(), TimeRemainingColumn())
            self._bar = Progress(*columns, console=stderr, transient=True)
            self._bar.start()
            self._task = self._bar.add_task("batch", total=to_fit, failed=0, rate="")

    def row(self, row: dict[str, Any]) -> None:
        self.done += row["status"] == "done"
        self.failed += row["status"] == "failed"
        if self.json_out:
            print(json.dumps(row), flush=True)
        now = time.perf_counter()
        finished = self.done + self.failed
        rate = f"{60 * finished / max(now - self.started, 1e-9):.1f}/min"
        if self._bar is not None:
            self._bar.update(self._task, completed=finished, failed=self.failed, rate=rate)
        elif not self.quiet and (now - self.last >= PROGRESS_LINE_SECONDS or finished == self.total):
            self.last = now
            print(f"statfit: batch: {finished}/{self.total} ({self.failed} failed), {rate}, {now - self.started:.0f} s",
                  file=sys.stderr, flush=True)

    def stop(self) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None


def _summary(report: BatchReport, out_dir: Path, quiet: bool, json_out: bool) -> None:
    median = statistics.median(report.seconds) if report.seconds else None
    if json_out:
        print(json.dumps(dict(event="summary", done=report.done, failed=len(report.failed), skipped=report.skipped,
                              median_seconds=median, wall_seconds=report.wall_seconds)))
    if quiet:
        return
    table = Table(title=f"batch → {out_dir}", title_justify="left")
    for column in ("done", "failed", "skipped (already done)", "median s per fit", "wall s"):
        table.add_column(column, justify="right")
    table.add_row(str(report.done), str(len(report.failed)), str(report.skipped),
                  "-" if median is None else f"{median:.2f}", f"{report.wall_seconds:.1f}")
    stderr.print(table)
    for source, reason in report.failed[:20]:
        stderr.print(f"  failed: {source}: {reason}", highlight=False, markup=False)
    if len(report.failed) > 20:
        stderr.print(f"  … {len(report.failed) - 20} more: statfit batch status {out_dir}", highlight=False)


def _run(items, job: FitJob, out_dir: Path, workers, scheduler, cluster, timeout, force, quiet, json_out) -> None:
    engine, share = _engine(workers, scheduler, cluster)
    job = dataclasses.replace(job, max_threads=share)
    progress = _Progress(quiet, json_out)
    try:
        with _terminate_as_interrupt():
            report = run_batch(items, job, out_dir, engine, force=force, timeout=timeout,
                               on_start=progress.start, on_row=progress.row)
    except KeyboardInterrupt:
        progress.stop()
        print(f"statfit: interrupted after {progress.done} done and {progress.failed} failed; every finished "
              "input is recorded: rerun the same command to go on", file=sys.stderr)
        raise SystemExit(EXIT_INTERRUPTED)
    finally:
        progress.stop()
        engine.close()
    _summary(report, out_dir, quiet, json_out)
    if report.failed:
        raise SystemExit(EXIT_FAILED)


@app.command("register")
def batch_register(
    inputs: list[str] = InputsArgument,
    out_dir: Path = OutDirOption,
    model_path: Path = ModelOption,
    k: int = KOption,
    method: str = MethodOption,
    preset: str = PresetOption,
    workers: int = WorkersOption,
    scheduler: str = SchedulerOption,
    cluster: str = ClusterOption,
    timeout: float = TimeoutOption,
    force: bool = ForceOption,
    align: str = typer.Option("auto", help="Pre-alignment of each scan: auto (pose, scale and units found), none, "
                              "rigid or similarity (see `statfit register --help`)."),
    region: str = typer.Option(None, "--region", help="Fit only the model's region NAME (see `statfit register "
                               "--help`).", show_default=False),
    refresh: int = typer.Option(10, help="Recompute closest surface points every N iterations.",
                                callback=within(1, 100_000)),
    trim: float = typer.Option(0.05, help="Fraction of farthest scan points ignored.", callback=within(0, 0.99)),
    clutter: str = ClutterOption,
    device: str = DeviceOption,
    threads: int = BatchThreadsOption,
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
        statfit batch status fits/
    """
    _check_engine(scheduler, cluster)
    stages = resolve(method, preset, **setting_overrides(iterations, lr, beta, power, lam, laplacian, mode_gain))
    if align not in SCAN_ALIGNMENTS:
        raise StatfitError(f"unknown alignment {align!r}; choose one of {', '.join(SCAN_ALIGNMENTS)}")
    model_file, digest, model = _model_identity(model_path, k)
    if region is not None:
        region_vertices(model, region)
    items = _prepared(inputs, out_dir)
    job = FitJob("register", model_file, k, stages, dict(align=align, region=region, refresh_every=refresh,
                                                         trim=trim, seed=seed, clutter=clutter_choice(clutter)),
                 threads=threads, device=str(resolve_device(device)), model_digest=digest)
    _run(items, job, out_dir, workers, scheduler, cluster, timeout, force, quiet, json_out)


@app.command("render")
def batch_render(
    inputs: list[str] = InputsArgument,
    out_dir: Path = OutDirOption,
    camera_path: Path = typer.Option(None, "--camera", "-c", help="One camera JSON for every map. Default: each "
                                     "map's own camera, from its EXR header.", show_default=False),
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
    align: str = typer.Option("rigid", help="Initial alignment: rigid, similarity or none (see `statfit render "
                              "--help`)."),
    normal_space: str = typer.Option("world", help="Frame of the maps' normals: world or camera."),
    normal_convention: str = typer.Option("opencv", help="Axes of camera-space normals: opencv or opengl."),
    silhouette_weight: float = typer.Option(SILHOUETTE_WEIGHT, help="Weight of the silhouette term (0: off).",
                                            callback=within(0, 1e6)),
    region: str = typer.Option(None, "--region", help="Fit only the model's region NAME.", show_default=False),
    device: str = DeviceOption,
    threads: int = BatchThreadsOption,
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
    """
    _check_engine(scheduler, cluster)
    if camera_path is not None and camera_from_header:
        raise StatfitError("use either --camera FILE or --camera-from-header, not both")
    stages = render_stages(method, preset, region,
                           **setting_overrides(iterations, lr, beta, power, lam, laplacian, mode_gain))
    for value, allowed, name in ((align, ALIGNMENTS, "alignment"), (normal_space, NORMAL_SPACES, "normal space"),
                                 (normal_convention, NORMAL_CONVENTIONS, "normal convention")):
        if value not in allowed:
            raise StatfitError(f"unknown {name} {value!r}; choose one of {', '.join(allowed)}")
    camera = None
    if camera_path is not None:
        read_camera(camera_path)  # checked once, here
        camera = str(camera_path.resolve())
    model_file, digest, model = _model_identity(model_path, k)
    if region is not None:
        region_vertices(model, region)
    items = _prepared(inputs, out_dir)
    job = FitJob("render", model_file, k, stages,
                 dict(camera=camera, align=align, normal_space=normal_space, normal_convention=normal_convention,
                      silhouette_weight=silhouette_weight, region=region, seed=seed),
                 threads=threads, device=str(resolve_device(device)), model_digest=digest)
    _run(items, job, out_dir, workers, scheduler, cluster, timeout, force, quiet, json_out)


@app.command("status")
def status(
    out_dir: Path = typer.Argument(..., metavar="OUT_DIR", help="A batch's output folder.", show_default=False),
    json_out: bool = typer.Option(False, "--json", help="Print the status as one JSON object on stdout."),
) -> None:
    """Where the latest batch in OUT_DIR stands: inputs done, failed (with their reasons) and pending."""
    state = batch_status(out_dir)
    if json_out:
        print(json.dumps(dict(done=len(state.done), failed=[dict(input=s, error=e) for s, e in state.failed],
                              pending=state.pending)))
        return
    table = Table(title=f"batch {out_dir} ({state.settings.get('command', '?')})", title_justify="left")
    for column in ("done", "failed", "pending"):
        table.add_column(column, justify="right")
    table.add_row(str(len(state.done)), str(len(state.failed)), str(len(state.pending)))
    console = Console()
    console.print(table)
    for source, reason in state.failed:
        console.print(f"failed: {source}: {reason}", highlight=False, markup=False)
    if state.pending:
        console.print("pending inputs finish when the same batch command is run again", highlight=False)
