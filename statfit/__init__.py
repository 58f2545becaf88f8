"""statfit: fit a template mesh to limited observations with statistical gradient filtering.

The public names below are imported on first use (PEP 562), so ``import statfit.errors`` or a
light submodule does not pull in torch, trimesh and SciPy: the command line's ``--help`` and its
one-line refusals of bad options start in a fraction of a second (docs/benchmarks.md §17)."""
from __future__ import annotations

import importlib
from importlib import metadata
from typing import Any

__version__ = metadata.version("statfit")

# public name → the module that defines it
_PUBLIC = {
    "StatModel": "statfit.model.statmodel", "load_model": "statfit.model.statmodel",
    "model_from_arrays": "statfit.model.statmodel", "save_model": "statfit.model.statmodel",
    "import_model": "statfit.model.importers",
    "build_model": "statfit.model.build", "build_model_from_files": "statfit.model.build",
    "reconstruct": "statfit.render.job", "reconstruct_many": "statfit.render.many",
    "register": "statfit.registration.job", "register_many": "statfit.registration.many",
    "Fit": "statfit.core.stages",
    "StatfitError": "statfit.errors", "DivergenceError": "statfit.errors",
}

__all__ = [*_PUBLIC, "__version__"]


def __getattr__(name: str) -> Any:
    if name not in _PUBLIC:
        raise AttributeError(f"module 'statfit' has no attribute {name!r}")
    value = getattr(importlib.import_module(_PUBLIC[name]), name)
    globals()[name] = value     # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
