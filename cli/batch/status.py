"""``statfit batch status``: where the latest batch in a folder stands."""
from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from statfit.batch.manifest import batch_status


def status(
    out_dir: Path = typer.Argument(..., metavar="OUT_DIR", help="A batch's output folder.", show_default=False),
    json_out: bool = typer.Option(False, "--json", help="Print the status as one JSON object on stdout."),
) -> None:
    """Where the latest batch in OUT_DIR stands: inputs done, failed (with their reasons) and pending."""
    state = batch_status(out_dir)
    if json_out:
        print(json.dumps(dict(done=len(state.done), failed=[dict(input=s, error=e) for s, e in state.failed],
                              pending=state.pending)))
        return
    table = Table(title=f"batch {out_dir} ({state.settings.get('command', '?')})", title_justify="left")
    for column in ("done", "failed", "pending"):
        table.add_column(column, justify="right")
    table.add_row(str(len(state.done)), str(len(state.failed)), str(len(state.pending)))
    console = Console()
    console.print(table)
    for source, reason in state.failed:
        console.print(f"failed: {source}: {reason}", highlight=False, markup=False)
    if state.pending:
        console.print("pending inputs finish when the same batch command is run again", highlight=False)
