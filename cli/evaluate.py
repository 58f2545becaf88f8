"""``statfit eval``: errors of a fitted mesh against the ground truth."""
from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from statfit.errors import StatfitError
from statfit.io.mesh import read_mesh, read_points
from statfit.metrics import evaluate as evaluate_fit, observed_vertices


def evaluate(
    fit: Path = typer.Argument(..., help="Fitted mesh.", show_default=False),
    gt: Path = typer.Argument(..., help="Ground-truth mesh, same topology and vertex order.", show_default=False),
    scan: Path = typer.Option(None, help="The scan that was fitted: splits errors into observed vertices "
                              "(within 3 median point spacings of a scan point) and unobserved ones.",
                              show_default=False),
    json_out: bool = typer.Option(False, "--json", help="Print the report as JSON."),
) -> None:
    """Per-vertex errors ‖fit − gt‖ over all / observed / unobserved vertices, and the distance of
    observed ground-truth vertices to the fitted surface.

        statfit eval fit.ply gt.ply --scan scan.ply --json
    """
    fit_vertices, faces = read_mesh(fit)
    gt_vertices, gt_faces = read_mesh(gt)
    if fit_vertices.shape != gt_vertices.shape or faces.shape != gt_faces.shape or (faces != gt_faces).any():
        raise StatfitError(f"{fit} and {gt} do not share a topology ({len(fit_vertices)} vs {len(gt_vertices)} vertices)")
    observed = observed_vertices(gt_vertices, read_points(scan)) if scan is not None else None
    report = evaluate_fit(fit_vertices, gt_vertices, faces, observed)
    if json_out:
        print(json.dumps(report))
        return
    table = Table(title=f"{fit.name} vs {gt.name} (model RMS radius {report['scale']:.4g})")
    for column in ("vertices", "count", "mean", "median", "max", "mean / radius"):
        table.add_column(column, justify="right")
    for name, row in report.items():
        if isinstance(row, dict):
            table.add_row(name, str(row["count"]), f"{row['mean']:.4g}", f"{row['median']:.4g}",
                          f"{row['max']:.4g}", f"{row['mean_rel']:.4f}")
    Console().print(table)
