"""How often a render fit refreshes its renderer's visibility (docs/method.md, "Visibility reused")."""
from __future__ import annotations

import torch

from statfit.core.graphs import graphs_capture

# Fitting calls per refresh: 4, in the fit's stages only (the alignment refreshes every call). Chosen on
# ICT's jaw-open and smile maps at 512²; checked on ICT's rendering study, §18's cross-family cases and
# the body study, and on new people: every set's error within its nudge floor; an iteration 0.62-0.63x and
# the whole fit 0.67-0.69x as long at 512² (docs/studies.md §31). Reused in the alignment too, it made
# cross-family fits up to 43% worse (§26).
VISIBILITY_EVERY = 4
# Pixels a vertex may move before the visibility is refreshed between those calls (None: never). Up to
# 16 calls with 1 px (alignment included): 0.55x the time, cross-family fits 4% better on average,
# bodies 15% worse (docs/studies.md §27: measured, not shipped).
VISIBILITY_MOVED: float | None = None
# Whether the render alignment's objective reuses the visibility by the fit's rules: no. Where it did,
# §26's every-4 and §27's 1 px moved bodies by -43% to +72% and §18's cross-family cases by up to 43%;
# with the alignment refreshing every call, every set stays within its nudge floor (docs/studies.md §31).
VISIBILITY_IN_ALIGNMENT = False


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


def alignment_visibility(visibility_every: int, visibility_moved: float | None) -> dict:
    """The alignment objective's keyword arguments for the fit's rules: the same, or every call where
    the alignment does not reuse the visibility (:data:`VISIBILITY_IN_ALIGNMENT`)."""
    if not VISIBILITY_IN_ALIGNMENT:
        return {"visibility_every": 1, "visibility_moved": None}
    return {"visibility_every": visibility_every, "visibility_moved": visibility_moved}
