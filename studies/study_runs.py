"""What a study script's command line does with its cases: run them two at a time, keep the rows,
print the tables."""
from __future__ import annotations

import json
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Callable


def run_or_report(run_case: Callable[..., dict], runs: list[tuple], results: Path,
                  report: Callable[[list[dict]], str], only_report: bool,
                  key: Callable[[dict], tuple] | None = None) -> None:
    """Unless ``only_report``, ``run_case(*run)`` for every run of ``runs``, two at a time in fresh
    (spawned, so no torch state is shared) processes, its rows stored in ``results`` (JSON); then
    print ``report`` of the stored rows. With ``key`` (a row → the run tuple that made it), the rows
    already stored are kept and only the runs they lack are run."""
    if not only_report:
        kept = json.loads(results.read_text()) if key is not None and results.is_file() else []
        done = {key(row) for row in kept} if key is not None else set()
        todo = [run for run in runs if tuple(run) not in done]
        with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
            rows = list(pool.map(run_case, *zip(*todo))) if todo else []
        results.write_text(json.dumps(kept + rows, indent=1))
    print(report(json.loads(results.read_text())))
