"""``statfit demo``: a partial scan of the embedded model, fitted by every method."""
from __future__ import annotations

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from statfit_cli.common import progress_bar, seed_option, within


def demo(
    seed: int = seed_option(3, "Seed of the synthetic target and scan."),
    yaw: float = typer.Option(30.0, help="View of the partial scan, degrees.", callback=within(-360, 360)),
    iterations: int = typer.Option(None, help="Iterations for every method (default: each method's own).",
                                   show_default=False),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars."),
) -> None:
    """Synthesise a partial scan from the embedded default model and fit it with every method.

    The target is a random head from the model (seen from one side, 4,300 points); the table
    shows each method's mean per-vertex error against the ground truth, split into vertices the
    scan observed and those it did not, and the time taken.
    """
    from statfit.core.methods import METHODS, resolve
    from statfit.geometry.metrics import evaluate, observed_vertices
    from statfit.model.importers.cache import open_model
    from statfit.registration.job import register as fit_scan
    from statfit.synth.sample import sample_target, scan_from_view

    model = open_model(None)
    rng = np.random.default_rng(seed)
    target = sample_target(model, rng, sigma=1.5)
    points = scan_from_view(target, model.faces, rng, 4300, yaw)
    observed = observed_vertices(target, points)
    unit = 1000.0  # the embedded model is in metres; report millimetres
    table = Table(title=f"statfit demo: {model.num_vertices}-vertex synthetic head, scan of {len(points)} points "
                        f"from yaw {yaw:g}° ({observed.mean():.0%} of vertices observed); errors in mm")
    for column in ("method", "all", "observed", "unobserved", "surface (observed)", "seconds"):
        table.add_column(column, justify="right")
    base = evaluate(model.template, target, model.faces, observed)
    table.add_row("(template)", *(f"{base[k]['mean'] * unit:.2f}" for k in ("all", "observed", "unobserved",
                                                                          "observed_surface")), "-")
    for method in ("default", *(name for name, entry in METHODS.items() if "register" in entry.tuned)):
        total = sum(stage.iterations for stage in resolve(method, iterations=iterations))
        with progress_bar(total, method, not quiet) as advance:
            result = fit_scan(model, points, method, iterations=iterations, on_record=advance, seed=seed)
        report = evaluate(result.vertices, target, model.faces, observed)
        table.add_row(method, *(f"{report[k]['mean'] * unit:.2f}" for k in ("all", "observed", "unobserved",
                                                                          "observed_surface")),
                      f"{result.seconds:.1f}")
    console = Console()
    console.print(table)
    console.print("The target is a model sample, inside the model's span, so pca can reach it exactly; for targets "
                  "with detail outside the model (ICT expressions) see docs/studies.md.")
