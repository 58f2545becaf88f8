"""The batch loop: skip what is done, run the rest on an engine, and record each input as it
finishes — output first (atomically), then its manifest line.

Failures stay with their input: a bad input is a ``failed`` line with the fit's one-line error; a
fit running past ``timeout`` is failed and its worker replaced; when a worker dies, the fits it may
have taken down are rerun one at a time, so only the one that kills its worker alone is failed.
With ``job.together`` > 1 a worker fits up to that many inputs in one program (``group_work``;
fewer where the workers would otherwise idle); a group that kills its worker or runs past
``timeout`` × its size is rerun an input at a time.
"""
from __future__ import annotations

import hashlib
import time
from collections import deque
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

from statfit.batch.engines import Engine, WorkerLost
from statfit.batch.fits import FitJob, Outcome, run_group, run_job
from statfit.batch.manifest import MANIFEST_NAME, Manifest, is_current, latest_fits, read_rows, settings_key
from statfit.batch.plan import Item, companion_file, file_digest
from statfit.errors import StatfitError
from statfit.io.files import write_atomic

POLL_SECONDS = 0.5
WORKER_DIED = "the worker died while fitting this input (a crash, or out of memory)"


@dataclass
class BatchReport:
    """What a run did: inputs fitted, failed (with reasons) and skipped as already done."""
    done: int = 0
    skipped: int = 0
    failed: list[tuple[str, str]] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)
    wall_seconds: float = 0.0


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


class _Recorder:
    """Writes each finished input's output and manifest line, and keeps the report."""

    def __init__(self, manifest: Manifest, out_dir: Path, key: str, report: BatchReport,
                 on_row: Callable[[dict[str, Any]], None] | None):
        self.manifest, self.out_dir, self.key, self.report, self.on_row = manifest, out_dir, key, report, on_row
        self.folders: set[Path] = set()  # output folders made so far

    def record(self, item: Item, digest: str | None, outcome: Outcome) -> None:
        row = dict(event="fit", input=item.identity, sha256=digest,
                   output=str(item.output.relative_to(self.out_dir)), key=self.key, seconds=round(outcome.seconds, 3),
                   finished=_now())
        error = outcome.error
        if error is None and outcome.data is not None:
            try:
                if item.output.parent not in self.folders:
                    item.output.parent.mkdir(parents=True, exist_ok=True)
                    self.folders.add(item.output.parent)
                write_atomic(item.output, outcome.data)
                for suffix, data in outcome.extras.items():   # beside the output: fit.ply → fit.params.json
                    write_atomic(item.output.with_suffix(suffix), data)
            except StatfitError as exc:  # write_atomic's message names the file
                error = str(exc)
            except OSError as exc:
                error = f"cannot create {item.output.parent}: {exc.strerror}"
        if error is None:
            row.update(status="done", bytes=len(outcome.data), summary=outcome.summary)
            self.report.done += 1
            self.report.seconds.append(outcome.seconds)
        else:
            row.update(status="failed", error=error)
            self.report.failed.append((str(item.source), error))
        self.manifest.append(row)
        if self.on_row is not None:
            self.on_row(row)


def plan_work(items: list[Item], out_dir: Path, key: str, force: bool, companion: tuple[str, str] | None = None
              ) -> tuple[list[tuple[Item, str | None]], list[tuple[Item, str]], int]:
    """(to fit with its digest, unreadable with the reason, number already done). With a
    ``companion`` (template, what it holds: :attr:`statfit.batch.fits.FitJob.companion`), an input's
    digest covers its own such file too, so a changed file is fitted again; an input without one is
    unreadable."""
    latest = latest_fits(read_rows(out_dir / MANIFEST_NAME))
    todo, unreadable, skipped = [], [], 0
    for item in items:
        path = companion_file(item.source, companion[0]) if companion is not None else None
        try:
            digest = file_digest(item.source)
            if path is not None:
                if not path.is_file():
                    unreadable.append((item, f"no {companion[1]} file {path} for {item.source}"))
                    continue
                digest = hashlib.sha256(f"{digest} {file_digest(path)}".encode()).hexdigest()
        except OSError as exc:
            unreadable.append((item, f"cannot read {exc.filename or item.source}: {exc.strerror}"))
            continue
        if not force and is_current(latest.get(item.identity), key, digest, out_dir):
            skipped += 1
        else:
            todo.append((item, digest))
    return todo, unreadable, skipped


def run_batch(items: list[Item], job: FitJob, out_dir: Path, engine: Engine, *, force: bool = False,
              timeout: float | None = None, work: Callable[[FitJob, str], Outcome] = run_job,
              group_work: Callable[[FitJob, list[str]], list[Outcome]] = run_group,
              on_start: Callable[[int, int], None] | None = None,
              on_row: Callable[[dict[str, Any]], None] | None = None) -> BatchReport:
    """Fit every item not already done with ``job``'s settings (all with ``force``) on ``engine``,
    recording each in ``out_dir``'s manifest. ``on_start(to_fit, skipped)`` is called once the plan
    is known, ``on_row(row)`` after every manifest line. ``work(job, source)`` replaces the fit
    (benchmarks of the bookkeeping), ``group_work(job, sources)`` the fit of a group of inputs
    (``job.together`` > 1). KeyboardInterrupt stops the engine and propagates; what was recorded
    stays."""
    started = time.perf_counter()
    key = settings_key(job.settings())
    report = BatchReport()
    with Manifest(out_dir / MANIFEST_NAME) as manifest:
        for stale in out_dir.rglob(".statfit-*.tmp"):  # a killed run's half-written output; ours alone (locked)
            stale.unlink(missing_ok=True)
        todo, unreadable, report.skipped = plan_work(items, out_dir, key, force, job.companion)
        manifest.append(dict(event="run", started=_now(), key=key, settings=job.settings(),
                             inputs=[item.identity for item in items]))
        if on_start is not None:
            on_start(len(todo) + len(unreadable), report.skipped)
        recorder = _Recorder(manifest, out_dir, key, report, on_row)
        for item, reason in unreadable:
            recorder.record(item, None, Outcome(None, {}, reason, 0.0))
        _drive(todo, job, engine, work, group_work, timeout, recorder)
    report.wall_seconds = time.perf_counter() - started
    return report


def _drive(todo: list[tuple[Item, str | None]], job: FitJob, engine: Engine, work: Callable, group_work: Callable,
           timeout: float | None, recorder: _Recorder) -> None:
    # Groups of at most ``job.together`` inputs, fewer where that keeps every worker busy (each
    # runs its group's pose searches one after another).
    size = max(1, min(job.together, -(-len(todo) // max(engine.workers, 1))))
    queue = deque(todo[i:i + size] for i in range(0, len(todo), size))
    suspects: deque[tuple[Item, str | None]] = deque()  # in flight when a worker died: rerun alone
    running: dict[Any, list] = {}  # future → [group, alone]; submission order = start order
    started: dict[Any, float] = {}  # the futures a worker has taken (the oldest ``engine.workers``), since when

    def submit(group: list[tuple[Item, str | None]], alone: bool) -> None:
        sources = [str(item.source) for item, _ in group]
        future = engine.submit(work, job, sources[0]) if len(group) == 1 else engine.submit(group_work, job, sources)
        running[future] = [group, alone]

    while queue or suspects or running:
        if suspects and not running:
            submit([suspects.popleft()], alone=True)
        while queue and not suspects and len(running) < engine.capacity:
            submit(queue.popleft(), alone=False)
        for future in list(running)[:engine.workers]:
            started.setdefault(future, time.monotonic())
        for future in engine.wait(running, POLL_SECONDS):
            group, alone = running.pop(future)
            started.pop(future, None)
            try:
                result = engine.result(future)
            except WorkerLost:
                if alone:
                    recorder.record(*group[0], Outcome(None, {}, WORKER_DIED, 0.0))
                else:
                    suspects.extend(group)
                continue
            for (item, digest), outcome in zip(group, result if isinstance(result, list) else [result]):
                recorder.record(item, digest, outcome)
        if timeout is not None:
            now = time.monotonic()
            hung = [f for f, start in started.items() if now - start > timeout * len(running[f][0])]
            if hung:
                stopped = engine.replace(hung, list(running))
                for future in hung:
                    group, _ = running.pop(future)
                    seconds = now - started.pop(future)
                    if len(group) > 1:       # which of them hangs: each alone, with its own limit
                        suspects.extend(group)
                    else:
                        recorder.record(*group[0], Outcome(None, {}, f"timed out after {timeout:g} s", seconds))
                for future in reversed(stopped):  # stopped with the hung one's worker: rerun first, not blamed
                    group, _ = running.pop(future)
                    started.pop(future, None)
                    queue.appendleft(group)
