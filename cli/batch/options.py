"""The options every fitting command of ``statfit batch`` shares, and its exit codes."""
from __future__ import annotations

from pathlib import Path

import typer

from statfit.batch.manifest import MANIFEST_NAME
from statfit.batch.plan import Item, expand_inputs, plan_outputs
from statfit.errors import StatfitError
from statfit_cli.common import within

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


def planned_inputs(inputs: list[str], out_dir: Path) -> list[Item]:
    """Every input with its output under ``out_dir``, said before a command loads the library:
    patterns that match no file, two outputs that would clash and an ``--out-dir`` that is a file
    are refused in one line. Nothing is created."""
    if out_dir.exists() and not out_dir.is_dir():
        raise StatfitError(f"--out-dir is a file: {out_dir}")
    return plan_outputs(expand_inputs(inputs, exclude=out_dir), out_dir)

