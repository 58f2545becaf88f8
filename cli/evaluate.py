"""``statfit eval``: errors of a fitted mesh against the ground truth."""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from statfit.errors import StatfitError
from statfit_cli.common import refuse_missing


MILLIMETRES_PER_UNIT = {"metres": 1000.0, "centimetres": 10.0, "millimetres": 1.0}

def evaluate(
    fit: Path = typer.Argument(..., help="Fitted mesh.", show_default=False),
    gt: Path = typer.Argument(..., help="Ground-truth mesh, same topology and vertex order.", show_default=False),
    scan: Path = typer.Option(None, help="The scan that was fitted: splits errors into observed vertices "
                              "(within 3 median point spacings of a scan point) and unobserved ones.",
                              show_default=False),
    normals: Path = typer.Option(None, help="The normal map that was fitted: observed vertices are those of the "
                                 "ground truth's triangles seen on its mask (needs a camera).", show_default=False),
    camera_path: Path = typer.Option(None, "--camera", help="Camera JSON of --normals (default: the EXR header's).",
                                     show_default=False),
    region: str = typer.Option(None, "--region", metavar="<name>",
                               help="Report only the vertices of the model's region NAME "
                               "(needs --model).", show_default=False),
    model_path: Path = typer.Option(None, "--model", "-m", help="The model the fit came from (any format "
                                    "--model takes elsewhere), for --region.", show_default=False),
    json_out: bool = typer.Option(False, "--json", help="Print the report as JSON."),
) -> None:
    """Per-vertex errors ‖fit − gt‖ over all / observed / unobserved vertices, and the distance of
    observed ground-truth vertices to the fitted surface. A fit PLY from register, render or splat
    carries its own split: without --scan/--normals its 'observed' field is used, and its
    'off_span' field splits the errors into quarters, off_span_q1 (the vertices nearest the
    model's span) to off_span_q4 (farthest).

        \b
        statfit eval fit.ply gt.ply --scan scan.ply --json
        statfit eval fit.ply gt.ply    # observed and off_span from the fit's PLY fields
        statfit eval fit.ply gt.ply --normals normals.exr --camera camera.json
        statfit eval fit.ply gt.ply --model flame.npz --region face
    """
    if scan is not None and normals is not None:
        raise StatfitError("give --scan or --normals, not both")
    if camera_path is not None and normals is None:
        raise StatfitError("--camera goes with --normals")
    refuse_missing({"file": [fit, gt, scan], "normal map": normals, "camera file": camera_path}, model_path)

    # The library loads once the paths are known good: a mistyped name is refused at once.
    from statfit.geometry.metrics import evaluate as evaluate_fit, observed_vertices
    from statfit.io.mesh import read_mesh, read_points, read_vertex_fields
    from statfit.model.statmodel import units_guess

    fit_vertices, faces = read_mesh(fit)
    gt_vertices, gt_faces = read_mesh(gt)
    if fit_vertices.shape != gt_vertices.shape or faces.shape != gt_faces.shape or (faces != gt_faces).any():
        raise StatfitError(f"{fit} and {gt} do not share a topology ({len(fit_vertices)} vs {len(gt_vertices)} vertices)")
    observed = None
    fields = read_vertex_fields(fit)
    if scan is not None:
        observed = observed_vertices(gt_vertices, read_points(scan))
    elif normals is not None:
        observed = _seen_vertices(gt_vertices, gt_faces, normals, camera_path)
    elif "observed" in fields:   # the fit's own record of what its data covered
        observed = fields["observed"] > 0.5
    if "off_span" in fields and not np.isfinite(fields["off_span"]).all():
        raise StatfitError(f"{fit}: its off_span field holds NaN or infinite values (statfit writes none)")
    report = evaluate_fit(fit_vertices, gt_vertices, faces, observed, _region_mask(model_path, region, len(fit_vertices)),
                          fields.get("off_span"))
    if json_out:
        print(json.dumps(_json_numbers(report), allow_nan=False))
        return
    units = units_guess(gt_vertices)
    to_mm = MILLIMETRES_PER_UNIT.get(units.split()[0])
    shown = "mm" if to_mm else "mesh units"
    note = f"units guessed from its size: {units}, shown in mm" if to_mm else "units unknown: shown as stored"
    table = Table(title=f"{fit.name} vs {gt.name} (RMS radius {report['scale'] * (to_mm or 1):.4g} {shown}; {note})")
    for column in ("vertices", "count", f"mean {shown}", f"median {shown}", f"max {shown}", "mean / radius"):
        table.add_column(column, justify="right")
    for name, row in report.items():
        if isinstance(row, dict):
            table.add_row(name, str(row["count"]), *(f"{row[k] * (to_mm or 1):.3f}" for k in ("mean", "median", "max")),
                          f"{row['mean_rel']:.4f}")
    Console().print(table)


def _region_mask(model_path: Path | None, region: str | None, num_vertices: int) -> np.ndarray | None:
    """(N,) bool of the region's vertices, or None without --region."""
    from statfit.model.importers.cache import open_model
    from statfit.model.statmodel import region_vertices

    if region is None:
        if model_path is not None:
            raise StatfitError("--model goes with --region")
        return None
    if model_path is None:
        raise StatfitError("--region needs --model (the model that holds the region)")
    model = open_model(model_path)
    if model.num_vertices != num_vertices:
        raise StatfitError(f"the model has {model.num_vertices} vertices, the fit {num_vertices}")
    mask = np.zeros(num_vertices, dtype=bool)
    mask[region_vertices(model, region)] = True
    return mask


def _seen_vertices(vertices: np.ndarray, faces: np.ndarray, normals: Path, camera_path: Path | None) -> np.ndarray:
    from statfit.geometry.metrics import visible_vertices
    from statfit.io.normalmap import camera_for_map, read_normal_map

    normal_map = read_normal_map(normals)
    seen = visible_vertices(vertices, faces, camera_for_map(normal_map, camera_path, normals), normal_map.mask)
    if not seen.any():
        raise StatfitError(f"the camera of {normals} sees no vertex of the ground truth in the map's foreground: are "
                           "they in the same frame and units?")
    return seen


def _json_numbers(value: Any) -> Any:
    """``value`` with NaN and infinite floats as None (JSON has no NaN: a row with no vertices, a
    ground truth without extent), nested dicts and lists included."""
    if isinstance(value, dict):
        return {key: _json_numbers(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_numbers(item) for item in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
