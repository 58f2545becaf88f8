"""How often a render fit refreshes its renderer's visibility (docs/method.md, "Visibility reused")."""
from __future__ import annotations

import torch

from statfit.core.graphs import graphs_capture

# Fitting calls per refresh: every call. Every 4 made ICT's default fits at 512² 0.57-0.59x as long and
# bodies 16% closer, but cross-family fits 1.9% worse on average and five of 18 by 7-43% (docs/studies.md
# §26: measured, not shipped).
VISIBILITY_EVERY = 1
# Pixels a vertex may move before the visibility is refreshed between those calls (None: never). Up to
# 16 calls with 1 px: 0.55x the time, cross-family fits 4% better on average, bodies 15% worse
# (docs/studies.md §27: measured, not shipped).
VISIBILITY_MOVED: float | None = None


def visibility_every(preset: str, device: torch.device) -> int:
    """Fitting calls per refresh of the visibility: :data:`VISIBILITY_EVERY`, or every call for the
    paper's preset (as nvdiffrast renders) and where a CUDA graph captures the fit (one program every
    call: :func:`statfit.core.graphs.graphs_capture`)."""
    return 1 if preset == "paper" or graphs_capture(device) else VISIBILITY_EVERY


def visibility_moved(preset: str, device: torch.device) -> float | None:
    """Pixels a vertex may move before the visibility is refreshed early: :data:`VISIBILITY_MOVED`
    where the visibility is reused at all (:func:`visibility_every`), else None."""
    return None if visibility_every(preset, device) == 1 else VISIBILITY_MOVED


def visibility_options(preset: str, device: torch.device) -> dict:
    """Both rules as the normal-map objective's keyword arguments (``visibility_every``,
    ``visibility_moved``)."""
    return {"visibility_every": visibility_every(preset, device), "visibility_moved": visibility_moved(preset, device)}
