"""Options and helpers shared by the commands."""
from __future__ import annotations

import sys
import warnings
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from statfit.model import StatModel, default_model_path, load_model

stderr = Console(stderr=True)

ModelOption = typer.Option(None, "--model", "-m", help="Model npz (v_template, faces, shapedirs). "
                           "Default: the embedded synthetic head.", show_default=False)
KOption = typer.Option(None, "--k", help="Use only the first K modes of the model.", show_default=False)


def open_model(path: Path | None, k: int | None = None) -> StatModel:
    """The model at ``path`` (or the embedded default), truncated to ``k`` modes."""
    return load_model(path or default_model_path(), k)


def warn(message: str) -> None:
    print(f"statfit: warning: {message}", file=sys.stderr)


@contextmanager
def printed_warnings() -> Iterator[None]:
    """Print library warnings as one line each."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    for item in caught:
        warn(str(item.message))


@contextmanager
def progress_bar(total: int, label: str, enabled: bool):
    """A rich progress bar on stderr when it is a terminal; yields ``advance(iteration, terms)``."""
    if not enabled or not sys.stderr.isatty():
        yield lambda iteration, terms: None
        return
    columns = (TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
               TextColumn("loss {task.fields[loss]}"), TimeElapsedColumn(), TimeRemainingColumn())
    with Progress(*columns, console=stderr, transient=True) as progress:
        task = progress.add_task(label, total=total, loss="-")

        def advance(iteration: int, terms: dict[str, float]) -> None:
            progress.update(task, completed=iteration + 1, loss=f"{terms.get('total', float('nan')):.3g}")

        yield advance
