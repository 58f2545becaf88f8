"""``statfit batch``: fit a dataset — many scans or normal maps, resumable, on a process pool or a
Dask cluster — and report where a batch stands. One module per command; :mod:`.running` holds what
the fitting commands share (engine, progress, summary)."""
from __future__ import annotations

import typer

from statfit_cli.batch.register import batch_register
from statfit_cli.batch.render import batch_render
from statfit_cli.batch.report import report
from statfit_cli.batch.status import status

app = typer.Typer(help="Fit datasets: many inputs, resumable, on local processes or a Dask cluster. "
                  "Exit codes: 0 every input done, 1 some failed (see `statfit batch status`), 2 the batch "
                  "could not start (bad options, no inputs), 130 interrupted (rerun the same command to resume).",
                  no_args_is_help=True)
app.command("register")(batch_register)
app.command("render")(batch_render)
app.command("status")(status)
app.command("report")(report)
