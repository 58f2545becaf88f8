"""The one way a command runs a fit: the log's header, a record every 10 iterations, progress on
stderr, library warnings as one line each, then the summary, the outputs written atomically (the
log last) and, with ``--json``, the summary on stdout."""
from __future__ import annotations

import json
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator

from statfit.io.jsonlog import JsonLinesLog, versions
from statfit.io.files import write_atomic
from statfit_cli.common import printed_warnings, progress_bar


class FitRun:
    """One fit's log and progress; ``on_record`` is the library's progress callback."""

    def __init__(self, log: JsonLinesLog, advance: Callable[[int, dict[str, float]], None]):
        self.log = log
        self.advance = advance
        self.started = time.perf_counter()

    def on_record(self, iteration: int, terms: dict[str, float]) -> None:
        self.advance(iteration, terms)
        self.log.write("record", iteration=iteration, **terms, elapsed=time.perf_counter() - self.started)


@contextmanager
def fit_run(command: str, log_path: str | Path | None, label: str, iterations: int, quiet: bool,
            **header: Any) -> Iterator[FitRun]:
    """Log ``header`` (plus the command and library versions) and show a progress bar over
    ``iterations`` while the block runs the fit with ``run.on_record``."""
    log = JsonLinesLog(log_path)
    log.write("header", command=command, **header, versions=versions())
    with progress_bar(iterations, label, not quiet) as advance, printed_warnings():
        yield FitRun(log, advance)


def finish(run: FitRun, summary: dict[str, Any], outputs: dict[str | Path, bytes], json_out: bool) -> None:
    """Log the summary, write every output (``'-'``: standard output) and then the log, atomically;
    print the summary as a JSON line with ``json_out``."""
    run.log.write("summary", **summary)
    for path, data in outputs.items():
        write_atomic(path, data)
    run.log.close()
    if json_out:
        print(json.dumps(summary))
