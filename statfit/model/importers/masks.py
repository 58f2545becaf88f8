"""Named vertex masks shipped beside a model (FLAME_masks.pkl: a dict name → vertex indices)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from statfit.errors import StatfitError
from statfit.io.files import existing_file
from statfit.io.npz import check_npz_sizes
from statfit.model.importers.safe_pickle import load_pickle


def read_masks(path: str | Path) -> dict[str, np.ndarray]:
    """A dict of name → vertex index array from a pickle (FLAME_masks.pkl, read without running code)
    or an npz."""
    path = existing_file(path, "mask file")
    if path.suffix.lower() == ".npz":
        try:
            check_npz_sizes(path, "mask file")
            with np.load(path, allow_pickle=False) as data:
                masks = {key: data[key] for key in data.files}
        except (OSError, ValueError, EOFError) as exc:
            raise StatfitError(f"cannot read {path}: {exc}") from None
    else:
        masks = load_pickle(path)
    if not isinstance(masks, dict) or not masks:
        raise StatfitError(f"{path}: expected a dict of region name → vertex indices, got {type(masks).__name__}")
    return {str(name): np.asarray(index) for name, index in masks.items()}
