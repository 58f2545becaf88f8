"""What a study script's command line does with its cases: run them two at a time, keep the rows,
print the tables."""
from __future__ import annotations

import json
import multiprocessing
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Callable


def run_or_report(run_case: Callable[..., dict], runs: list[tuple], results: Path,
                  report: Callable[[list[dict]], str], only_report: bool,
                  key: Callable[[dict], tuple] | None = None) -> None:
    """Unless ``only_report``, ``run_case(*run)`` for every run of ``runs``, two at a time in fresh
    (spawned, so no torch state is shared) processes, its rows stored in ``results`` (JSON); then
    print ``report`` of the stored rows. The rows are written as each run ends (a stopped study keeps
    what it measured), with a progress line. With ``key`` (a row → the run tuple that made it), the
    rows already stored are kept and only the runs they lack are run; without it, a run starts afresh."""
    if not only_report:
        rows = json.loads(results.read_text()) if key is not None and results.is_file() else []
        done = {key(row) for row in rows} if key is not None else set()
        todo = [run for run in runs if tuple(run) not in done]
        results.write_text(json.dumps(rows, indent=1))
        with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
            pending = [pool.submit(run_case, *run) for run in todo]
            for count, future in enumerate(as_completed(pending), 1):
                rows.append(future.result())
                results.write_text(json.dumps(rows, indent=1))
                print(f"{count}/{len(todo)}", *(rows[-1].get(k, "") for k in list(rows[-1])[:5]), flush=True)
    print(report(json.loads(results.read_text())))


def study_main(doc: str, run_case: Callable[..., dict], runs: Callable[[], list[tuple]], results: Path,
               report: Callable[[list[dict]], str], key: Callable[[dict], tuple]) -> None:
    """A study's command line: ``--report`` prints the stored rows' tables; otherwise the runs the
    stored rows lack are run first (:func:`run_or_report`)."""
    import argparse

    parser = argparse.ArgumentParser(description=doc.split("\n")[0])
    parser.add_argument("--report", action="store_true", help="only print the tables of the stored rows")
    args = parser.parse_args()
    run_or_report(run_case, [] if args.report else runs(), results, report, args.report, key=key)
