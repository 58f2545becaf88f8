"""What a study script's command line does with its cases: run them two at a time, keep the rows,
print the tables."""
from __future__ import annotations

import json
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Callable


def run_or_report(run_case: Callable[..., dict], runs: list[tuple], results: Path,
                  report: Callable[[list[dict]], str], only_report: bool) -> None:
    """Unless ``only_report``, ``run_case(*run)`` for every run of ``runs``, two at a time in fresh
    (spawned, so no torch state is shared) processes, its rows stored in ``results`` (JSON); then
    print ``report`` of the stored rows."""
    if not only_report:
        with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
            rows = list(pool.map(run_case, *zip(*runs)))
        results.write_text(json.dumps(rows, indent=1))
    print(report(json.loads(results.read_text())))
