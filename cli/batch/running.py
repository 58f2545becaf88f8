"""What ``statfit batch register`` and ``render`` share: the engine, the inputs' outputs, the model
opened once, the progress bar and the summary."""
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

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from statfit.batch.engines import DaskPool, Engine, LocalPool
from statfit.batch.fits import FitJob
from statfit.batch.run import BatchReport, run_batch
from statfit.core.threads import available_cores
from statfit.errors import StatfitError
from statfit.model.importers.cache import content_key, open_model
from statfit.model.statmodel import StatModel
from statfit_cli.batch.options import EXIT_FAILED, EXIT_INTERRUPTED
from statfit_cli.common import PROGRESS_LINE_SECONDS, stderr


def check_engine(scheduler: str | None, cluster: str | None) -> None:
    if scheduler is not None and cluster is not None:
        raise StatfitError("use either --scheduler ADDRESS or --cluster local, not both")
    if cluster is not None and cluster != "local":
        raise StatfitError(f"--cluster takes 'local' (a Dask LocalCluster), got {cluster!r}")


def engine_for(workers: int | None, scheduler: str | None, cluster: str | None) -> tuple[Engine, int | None]:
    """The engine and the thread cap of each of its fits."""
    count = workers or available_cores()
    share = max(1, available_cores() // count)
    if scheduler is not None:
        return DaskPool(scheduler, count), None
    if cluster is not None:
        return DaskPool("local", count, share), share
    return LocalPool(count, share), share


def create_out_dir(out_dir: Path) -> None:
    """``out_dir`` and its parents, once every check has passed; one line where it cannot be made."""
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StatfitError(f"cannot create {out_dir}: {exc.strerror}") from None


def model_identity(model_path: Path | None, k: int | None) -> tuple[str | None, str, StatModel]:
    """The model's path for the workers, its content digest (for the settings key), and the model,
    opened here once so that a bad model stops the batch before it starts."""
    model = open_model(model_path, k)
    digest = content_key(model_path, {}) if model_path is not None else model.source
    return (str(model_path.resolve()) if model_path is not None else None), digest, model


@contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM (a scheduler ending the job) stops the batch as Ctrl-C does."""
    def interrupt(signum, frame):
        raise KeyboardInterrupt
    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class BatchProgress:
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


def print_summary(report: BatchReport, out_dir: Path, quiet: bool, json_out: bool) -> None:
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


def run_fits(items, job: FitJob, out_dir: Path, workers, scheduler, cluster, timeout, force, quiet, json_out) -> None:
    engine, share = engine_for(workers, scheduler, cluster)
    job = dataclasses.replace(job, max_threads=share)
    progress = BatchProgress(quiet, json_out)
    try:
        with terminate_as_interrupt():
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
    print_summary(report, out_dir, quiet, json_out)
    if report.failed:
        raise SystemExit(EXIT_FAILED)
