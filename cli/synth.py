"""``statfit synth``: test data with a known ground truth."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from statfit.errors import StatfitError
from statfit.io.mesh import check_writable, mesh_bytes, mesh_format, points_bytes, write_atomic
from statfit.synth import load_delta, sample_target, scan_from_view
from statfit_cli.common import ModelOption, open_model

app = typer.Typer(help="Make synthetic test data from a model, with its ground truth.", no_args_is_help=True)


@app.command("scan")
def scan(
    out: Path = typer.Option(..., "--out", "-o", help="Scan point cloud (PLY).", show_default=False),
    gt: Path = typer.Option(None, help="Ground-truth mesh (template topology).", show_default=False),
    model_path: Path = ModelOption,
    seed: int = typer.Option(0, help="Seed of the shape and of the point sampling."),
    sigma: float = typer.Option(1.0, help="Coefficients ~ N(0, sigma²) in std-dev units."),
    yaw: float = typer.Option(30.0, help="View direction, degrees about +y (0 looks at the +z face)."),
    pitch: float = typer.Option(0.0, help="View elevation, degrees."),
    points: int = typer.Option(4300, help="Number of scan points."),
    noise: float = typer.Option(0.0, help="Gaussian noise, as a fraction of the shape's RMS radius."),
    outliers: float = typer.Option(0.0, help="Fraction of points replaced by uniform outliers."),
    delta: Path = typer.Option(None, help="npz of off-model deltas (names (D,), deltas (N, 3, D)).",
                               show_default=False),
    delta_name: str = typer.Option(None, help="Which delta to add, e.g. jawOpen.", show_default=False),
    delta_weight: float = typer.Option(1.0, help="Weight of the delta."),
) -> None:
    """A model sample seen from one side: a partial scan plus its ground-truth mesh.

        statfit synth scan --model model.npz --seed 3 --out scan.ply --gt gt.ply
    """
    if (delta is None) != (delta_name is None):
        raise StatfitError("--delta and --delta-name go together")
    if points < 10:
        raise StatfitError("--points must be at least 10")
    if not 0 <= outliers < 1:
        raise StatfitError("--outliers must lie in [0, 1)")
    for target in (out, gt):
        if target is not None:
            check_writable(target)
    model = open_model(model_path)
    rng = np.random.default_rng(seed)
    offset = load_delta(str(delta), delta_name) if delta is not None else None
    shape = sample_target(model, rng, sigma, offset, delta_weight)
    cloud = scan_from_view(shape, model.faces, rng, points, yaw, pitch, noise, outliers)
    write_atomic(out, points_bytes(cloud))
    if gt is not None:
        write_atomic(gt, mesh_bytes(shape, model.faces, mesh_format(gt)))
