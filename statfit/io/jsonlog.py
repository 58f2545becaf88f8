"""JSON-lines fit logs: a header, periodic records, a summary; the file appears only when complete."""
from __future__ import annotations

import json
import platform
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import torch

from statfit.io.files import write_atomic


def versions() -> dict[str, str]:
    """Versions of the interpreter and the libraries that decide the numbers."""
    import scipy
    import trimesh

    return {"statfit": metadata.version("statfit"), "python": platform.python_version(), "torch": torch.__version__,
            "numpy": np.__version__, "scipy": scipy.__version__, "trimesh": trimesh.__version__}


class JsonLinesLog:
    """Collects log lines in memory and writes them atomically on ``close``."""

    def __init__(self, path: str | Path | None):
        self.path = path
        self.lines: list[str] = []

    def write(self, kind: str, **fields: Any) -> None:
        self.lines.append(json.dumps({"type": kind, **fields}, default=_plain))

    def close(self) -> None:
        if self.path is not None:
            write_atomic(self.path, ("\n".join(self.lines) + "\n").encode())


def _plain(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


