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

from statfit.errors import StatfitError
from statfit.importers.cache import open_any_model
from statfit.model import StatModel, default_model_path, load_model

stderr = Console(stderr=True)

ModelOption = typer.Option(None, "--model", "-m", help="Model npz (v_template, faces, shapedirs), or an "
                           "original model (FLAME/SMPL-X .pkl/.npz, ICT-FaceKit folder, BFM 2017 .h5): imported "
                           "once and cached in $STATFIT_CACHE_DIR (default ~/.cache/statfit). "
                           "Default: the embedded synthetic head.", show_default=False)
KOption = typer.Option(None, "--k", help="Use only the first K modes of the model.", show_default=False)
MethodOption = typer.Option("default", help="default (the measured best pipeline), statistical, hybrid, "
                            "laplacian, pca (register: closed-form Gauss-Newton, ~15x sooner than default), "
                            "regularized or none.")
PresetOption = typer.Option("tuned", help="tuned (our measured defaults) or paper (the paper's settings, exactly).")
DeviceOption = typer.Option("cpu", help="auto, cpu or cuda.")
ThreadsOption = typer.Option(None, help="CPU threads for the fit. Default: 1 for head-sized models (a second "
                             "thread gains little and stalls when the other core is busy), all cores for large ones.",
                             show_default=False)
SeedOption = typer.Option(0, help="Random seed; the same seed gives the same mesh.")
LogOption = typer.Option(None, help="JSON-lines log: header, a record every 10 iterations, summary.",
                         show_default=False)
QuietOption = typer.Option(False, "--quiet", "-q", help="No progress bar.")
JsonOption = typer.Option(False, "--json", help="Print each fit's summary as a JSON line on stdout.")
IterationsOption = typer.Option(None, help="Iterations (all stages together). Default: the method's.",
                                show_default=False)
LrOption = typer.Option(None, help="Step size (fit frame: model centred, unit RMS radius).", show_default=False)
BetaOption = typer.Option(None, help="β of the statistical/hybrid filter, or the regulariser's weight.",
                          show_default=False)
PowerOption = typer.Option(None, help="Exponent p on the statistical filter (same as β' = (1+β)^p − 1).",
                           show_default=False)
LamOption = typer.Option(None, help="λ of the Laplacian (laplacian, hybrid).", show_default=False)
LaplacianOption = typer.Option(None, help="uniform or cotangent.", show_default=False)
ModeGainOption = typer.Option(None, help="γ: filter gain on mode j = (std_j/std_1)^γ; 0 is the paper's filter.",
                              show_default=False)


def setting_overrides(iterations: int | None, lr: float | None, beta: float | None, power: float | None,
                      lam: float | None, laplacian: str | None, mode_gain: float | None) -> dict:
    """The method-setting options as overrides for :func:`statfit.methods.resolve` (validated)."""
    if laplacian is not None and laplacian not in ("uniform", "cotangent"):
        raise StatfitError(f"unknown Laplacian {laplacian!r}; choose uniform or cotangent")
    return dict(iterations=iterations, lr=lr, beta=beta, power=power, lam=lam, laplacian=laplacian,
                mode_gain=mode_gain)


def open_model(path: Path | None, k: int | None = None) -> StatModel:
    """The model at ``path`` in any format (imported and cached) or the embedded default, truncated
    to ``k`` modes."""
    return open_any_model(path, k=k) if path is not None else load_model(default_model_path(), k)


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
