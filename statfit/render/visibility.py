"""How often a render fit refreshes its renderer's visibility (docs/method.md, "Visibility reused")."""
from __future__ import annotations

import torch

from statfit.core.graphs import graphs_capture

# Fitting calls per refresh: every call. Every 4 made ICT's default fits at 512² 0.57-0.59x as long and
# bodies 16% closer, but cross-family fits 1.9% worse on average and five of 18 by 7-43% (docs/studies.md
# §26: measured, not shipped).
VISIBILITY_EVERY = 1


def visibility_every(preset: str, device: torch.device) -> int:
    """Fitting calls per refresh of the visibility: :data:`VISIBILITY_EVERY`, or every call for the
    paper's preset (as nvdiffrast renders) and where a CUDA graph captures the fit (one program every
    call: :func:`statfit.core.graphs.graphs_capture`)."""
    return 1 if preset == "paper" or graphs_capture(device) else VISIBILITY_EVERY
