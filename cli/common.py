"""Options and helpers shared by the commands."""
from __future__ import annotations

import math
import os
import sys
import time
import warnings
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from statfit.errors import StatfitError
from statfit.core.method_help import LANDMARK_WEIGHT, PCA_LANDMARK_WEIGHT, SUMMARIES
from statfit.io.files import existing_file, existing_folder, output_suffix

stderr = Console(stderr=True)

MAX_SEED = 2**32 - 1


def within(low: float | None = None, high: float | None = None, *, above: bool = False):
    """An option callback refusing NaN, infinities and values outside [low, high] (``above``: the
    low end excluded), so a bad number is one line before any work, whatever the command."""
    def check(value):
        if value is None:
            return value
        low_ok = low is None or (value > low if above else value >= low)
        if not (math.isfinite(value) and low_ok and (high is None or value <= high)):
            lower = "" if low is None else (f"> {low:g}" if above else f"≥ {low:g}")
            upper = "" if high is None else f"≤ {high:g}"
            bounds = " and ".join(b for b in (lower, upper) if b)
            raise typer.BadParameter(f"must be a finite number{' ' + bounds if bounds else ''}, got {value}")
        return value

    return check


def seed_option(default: int, help: str):
    """A seed option: a whole number from 0 to 2³² − 1."""
    return typer.Option(default, help=help, callback=within(0, MAX_SEED))

ModelOption = typer.Option(None, "--model", "-m", help="Model npz (v_template, faces, shapedirs), or an "
                           "original model (FLAME/SMPL-X .pkl/.npz, ICT-FaceKit folder, BFM 2017 .h5): imported "
                           "once and cached in $STATFIT_CACHE_DIR (default ~/.cache/statfit). "
                           "Default: the embedded synthetic head.", show_default=False)
KOption = typer.Option(None, "--k", help="Use only the first K modes of the model.", show_default=False)
MethodOption = typer.Option("default", help="default (the measured best pipeline) or one method: "
                            + "; ".join(f"{name}: {summary}" for name, summary in SUMMARIES.items())
                            + ". register's pca is the closed-form Gauss-Newton fit alone; its default adds 200 hybrid steps."
                            " render's default: two hybrid stages, then the Laplacian filter (docs/studies.md §13).")
FallbackOption = typer.Option(True, "--fallback/--no-fallback", help="register's default only: where its fit leaves "
                              "the scan it saw more than 2% of the model's radius away on average (points past or near "
                              "the model's open border, such as a face mask's neck, left out), or needs more than "
                              "3.5 standard deviations per mode, the person holds a shape the model cannot make and its "
                              "guess of the unseen part is unreliable: refit with "
                              "laplacian, said on stderr and in the summary's fallback (docs/method.md). Not with "
                              "--region, --preset paper or any setting overridden.")
PresetOption = typer.Option("tuned", help="tuned (our measured defaults) or paper (the paper's settings, exactly).")
DeviceOption = typer.Option("cpu", envvar="STATFIT_DEVICE", help="auto, cpu or cuda (default: $STATFIT_DEVICE, else cpu). auto: the GPU when "
                            "there is one and the command is not measured faster on the CPU (register stays there until "
                            "a whole command is measured faster on a card: docs/benchmarks.md §12), else the CPU.")
ThreadsOption = typer.Option(None, help="CPU threads for the fit, at most. Default: 1 for head-sized models (a "
                             "second thread gains little and stalls when the other core is busy); for large ones, the "
                             "cores idle when the fit starts. (register's pose search runs its 3 candidates side by "
                             "side on the cores there are.)",
                             show_default=False)
SeedOption = seed_option(0, "Random seed; the same seed gives the same mesh.")
LogOption = typer.Option(None, help="JSON-lines log: header, a record every 10 iterations, summary.",
                         show_default=False)
ParamsOption = typer.Option(None, "--params", help="Also write the fit's code in the model (.json or .npz): the "
                            "similarity model → data, the coefficients (standard deviations, one per mode) and what "
                            "the modes do not explain; `statfit model sample --params FILE` remakes the mesh "
                            "(docs/formats.md, \"Params file\"). E.g. --params fit.params.json", show_default=False)
QuietOption = typer.Option(False, "--quiet", "-q", help="No progress bar.")
LandmarkWeightOption = typer.Option(None, help="Weight of the landmark term against the scan's mean squared distance "
                                    "(robust: beyond ~5% of the model's radius off its place, a landmark pulls less the "
                                    "farther it is); 0: the start only.  [default: the method's: "
                                    f"{LANDMARK_WEIGHT:g}; pca {PCA_LANDMARK_WEIGHT:g}]",
                                    callback=within(0, 1e6), show_default=False)
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
    """The method-setting options as overrides for :func:`statfit.core.methods.resolve` (validated)."""
    if laplacian is not None and laplacian not in ("uniform", "cotangent"):
        raise StatfitError(f"unknown Laplacian {laplacian!r}; choose uniform or cotangent")
    return dict(iterations=iterations, lr=lr, beta=beta, power=power, lam=lam, laplacian=laplacian,
                mode_gain=mode_gain)


SilhouetteOption = typer.Option("auto", help="The silhouette term: two-sided (the model's outline matches the map's "
                                "mask), one-sided (only model outside the mask counts: a model of part of what the map "
                                "shows, e.g. a face mask in a photo of a head), covering (only mask the model leaves "
                                "uncovered counts: a map of part of what the model makes, e.g. a face cut out of a "
                                "photo by a skin mask, fitted with a head) or auto (one-sided for a model whose "
                                "surface faces one way, as a face mask's does; else two-sided).")

RigidModesOption = typer.Option("auto", "--rigid-modes", help="The model's modes as built (keep), or without the "
                                 "rigid motion of the template in them (drop: each mode's least-squares translation "
                                 "and rotation taken out, as `statfit model cut --without-rigid-motion` does; the "
                                 "fit finds the pose itself), or auto: drop it where it is more than 90% of what "
                                 "the modes do, as in a head cut from a body model (`statfit model info` prints the "
                                 "share; docs/method.md), and in render, up to 50%, also where the alignment moved "
                                 "the model off the place its modes give its people (a photo not taken in the "
                                 "model's frame), unless --align none without --landmarks. Fitting modes without "
                                 "rigid motion, register's closed form moves the pose a little itself. The mesh and "
                                 "--params are the given model's either way.")

# Without a terminal, a progress line at most this often (seconds).
PROGRESS_LINE_SECONDS = 5.0


def _now_and_then(label: str) -> Callable[[Callable[[], str]], None]:
    """``say(text)``: print "statfit: label: text(), Ns" on stderr if ``PROGRESS_LINE_SECONDS`` have
    passed since the last line (``text`` is only called then)."""
    started = last = time.perf_counter()

    def say(text: Callable[[], str]) -> None:
        nonlocal last
        now = time.perf_counter()
        if now - last >= PROGRESS_LINE_SECONDS:
            last = now
            print(f"statfit: {label}: {text()}, {now - started:.0f} s", file=sys.stderr, flush=True)

    return say


def _progress_lines(total: int, label: str):
    """``advance(iteration, terms)`` printing "label: iteration i/total, loss L, Ns" now and then."""
    say = _now_and_then(label)
    return lambda iteration, terms: say(lambda: f"iteration {iteration + 1}/{max(total, iteration + 1)}, "
                                                f"loss {terms.get('total', float('nan')):.4g}")


@contextmanager
def _rich_bar(label: str, total: int | None, *fields: TextColumn):
    """A transient rich progress bar on stderr with ``fields`` after the count; yields (progress, task)."""
    columns = (TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"), *fields,
               TimeElapsedColumn(), TimeRemainingColumn())
    with Progress(*columns, console=stderr, transient=True) as progress:
        yield progress, progress.add_task(label, total=total, loss="-")


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
    """A rich progress bar on stderr when it is a terminal, else (CI, nohup, a pipe) a plain line every
    ``PROGRESS_LINE_SECONDS``; yields ``advance(iteration, terms)``."""
    if not enabled:
        yield lambda iteration, terms: None
        return
    if not sys.stderr.isatty():
        yield _progress_lines(total, label)
        return
    with _rich_bar(label, total, TextColumn("loss {task.fields[loss]}")) as (progress, task):

        def advance(iteration: int, terms: dict[str, float]) -> None:
            # a refit (register's fallback) runs past the planned total: the bar grows with it
            progress.update(task, completed=iteration + 1, total=max(total, iteration + 1),
                            loss=f"{terms.get('total', float('nan')):.3g}")

        yield advance


@contextmanager
def count_bar(label: str, enabled: bool):
    """Progress of work counted in items (files read, inputs checked): a rich bar on stderr when it is
    a terminal, else a plain "label: done/total, Ns" line every ``PROGRESS_LINE_SECONDS``; yields
    ``advance(done, total)``."""
    if not enabled:
        yield lambda done, total: None
        return
    if not sys.stderr.isatty():
        say = _now_and_then(label)
        yield lambda done, total: say(lambda: f"{done}/{total}")
        return
    with _rich_bar(label, None) as (progress, task):
        yield lambda done, total: progress.update(task, completed=done, total=total)


@contextmanager
def stage_line(message: str, enabled: bool):
    """One stage of a long command said on stderr while it runs (a spinner on a terminal, else one line)."""
    if not enabled:
        yield
    elif sys.stderr.isatty():
        with stderr.status(message):
            yield
    else:
        print(f"statfit: {message}", file=sys.stderr, flush=True)
        yield


CLUTTER_CHOICES = {"auto": None, "on": True, "off": False}
ClutterOption = typer.Option("auto", help="Rules for scan points off the template (hair, shoulders, background): a "
                             "point counts only if its normal agrees with the surface's and it is not far beyond the "
                             "others. auto: on when the alignment finds points no shape of the model explains "
                             "(--align auto); on; off. Points beyond the template's open border never count.")


def clutter_choice(value: str) -> bool | None:
    """--clutter auto|on|off as register()'s ``clutter``."""
    if value not in CLUTTER_CHOICES:
        raise StatfitError(f"unknown --clutter {value!r}; choose auto, on or off")
    return CLUTTER_CHOICES[value]


# What a fit preview's views of the fitted mesh show: its normals, or a per-vertex field of its PLY.
PREVIEW_COLOURS = ("normals", "data_distance", "off_span", "observed")


def check_preview(path: Path | None, colour: str | None = None) -> None:
    """A ``--preview`` path (a PNG) and its ``--preview-colour``, refused before any work."""
    if colour is not None and colour not in PREVIEW_COLOURS:
        raise StatfitError(f"unknown --preview-colour {colour!r}; choose one of {', '.join(PREVIEW_COLOURS)}")
    if path is not None:
        output_suffix(path, (".png",), "a preview")


InputPath = str | Path | None


def refuse_missing(files: dict[str, InputPath | list[InputPath]], model: Path | None = None,
                   folders: dict[str, str | Path] | None = None) -> None:
    """The readers' one line for a mistyped input name, said before a command loads the library
    (~2 s of imports): each of ``files`` (what it is → its path, or a list of paths of that kind;
    None and '-' skipped) must be a file, each of ``folders`` a folder; ``model``, when given, a
    file or a folder (ICT-FaceKit's)."""
    for what, paths in files.items():
        for path in paths if isinstance(paths, list) else [paths]:
            if path is not None and str(path) != "-":
                existing_file(path, what)
    for what, path in (folders or {}).items():
        existing_folder(path, what)
    if model is not None and not Path(model).is_dir():
        existing_file(model, "model file")



def refuse_overwrite(outputs: dict[str, InputPath], inputs: dict[str, InputPath | list[InputPath]]) -> None:
    """Refuse, before any work, an output that names an input (the fit would change what it read)
    or another output (one of the two would be lost): ``outputs`` maps each output's option to its
    path, ``inputs`` what each input is to its path or paths; None and '-' are skipped. Paths are
    compared as the files they name (links and relative paths resolved)."""
    def same(a: InputPath, b: InputPath) -> bool:
        first, second = Path(str(a)), Path(str(b))
        if first.exists() and second.exists():
            return os.path.samefile(first, second)
        return first.resolve() == second.resolve()

    named = [(option, path) for option, path in outputs.items() if path is not None and str(path) != "-"]
    for index, (option, path) in enumerate(named):
        for what, paths in inputs.items():
            for source in paths if isinstance(paths, list) else [paths]:
                if source is not None and str(source) != "-" and same(path, source):
                    raise StatfitError(f"{option} {path} is the {what}: statfit never writes over its input; "
                                       "choose another path")
        for other, other_path in named[:index]:
            if same(path, other_path):
                raise StatfitError(f"{other} and {option} both name {path}; choose two paths")
