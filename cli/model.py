"""``statfit model``: inspect model files."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from statfit_cli.common import open_model

app = typer.Typer(help="Inspect statistical models.", no_args_is_help=True)


@app.command("info")
def info(
    model_path: Path = typer.Argument(None, help="Model npz. Default: the embedded synthetic head.",
                                      show_default=False),
    json_out: bool = typer.Option(False, "--json", help="Print as JSON."),
) -> None:
    """Vertices, faces, modes, variance explained and bounding box of a model."""
    model = open_model(model_path)
    explained = model.variance_explained()
    extent = np.ptp(model.template, axis=0)
    report = {
        "model": model.source, "vertices": model.num_vertices, "faces": int(len(model.faces)),
        "modes": model.num_modes, "std_first": float(model.std[0]), "std_last": float(model.std[-1]),
        "variance_explained": {str(k): float(explained[k - 1]) for k in (1, 5, 10, 20, 50, 100) if k <= model.num_modes},
        "bbox_extent": extent.tolist(), "landmarks": 0 if model.landmarks is None else int(model.landmarks.size),
        "regions": {name: int(idx.size) for name, idx in model.regions.items()},
    }
    if json_out:
        print(json.dumps(report))
        return
    table = Table(title=str(model.source), show_header=False)
    table.add_column("key")
    table.add_column("value")
    for key, value in report.items():
        if key == "model":
            continue
        if isinstance(value, dict):
            value = ", ".join(f"{k}: {v:.4g}" if isinstance(v, float) else f"{k}: {v}" for k, v in value.items()) or "-"
        elif isinstance(value, list):
            value = " × ".join(f"{v:.4g}" for v in value)
        elif isinstance(value, float):
            value = f"{value:.4g}"
        table.add_row(key.replace("_", " "), str(value))
    Console().print(table)
