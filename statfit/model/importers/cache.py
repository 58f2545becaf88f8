"""Import a model once: later uses of the same file (same bytes, same options) read a cached npz."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path

from statfit.errors import StatfitError
from statfit.model.importers import import_model, model_format, with_light_keys
from statfit.model.statmodel import StatModel, default_model_path, load_model, save_model


def cache_dir() -> Path:
    """``$STATFIT_CACHE_DIR``, else ``~/.cache/statfit``."""
    return Path(os.environ.get("STATFIT_CACHE_DIR") or Path.home() / ".cache" / "statfit")


def content_key(path: Path, options: dict) -> str:
    """sha256 of the options and the file's bytes (for a folder: each file's name and bytes)."""
    digest = hashlib.sha256(json.dumps(options, sort_keys=True).encode())
    for file in sorted(p for p in path.iterdir() if p.is_file()) if path.is_dir() else [path]:
        digest.update(file.name.encode() if path.is_dir() else b"")
        digest.update(file.read_bytes())
    return digest.hexdigest()


def open_any_model(path: str | Path, *, k: int | None = None, folder: Path | None = None,
                   **options) -> StatModel:
    """The model at ``path`` in any format (first ``k`` modes): an npz in the contract is read
    directly (with the light ICT-FaceKit layout's landmarks and face geometry, :func:`with_light_keys`);
    another format is imported with ``options`` once and cached in
    ``folder/models/<sha256>.npz`` (default folder: :func:`cache_dir`). A damaged cache entry is
    rebuilt; a cache that cannot be written is skipped."""
    path = Path(path)
    if model_format(path) == "statfit":
        return with_light_keys(load_model(path, k), path)
    entry = (folder or cache_dir()) / "models" / f"{content_key(path, options)}.npz"
    try:
        model = dataclasses.replace(load_model(entry), source=f"{path} (cached {entry.name[:12]})")
    except StatfitError:  # absent or damaged: import again
        model = import_model(path, **options)
        try:
            entry.parent.mkdir(parents=True, exist_ok=True)
            save_model(model, entry)
        except (OSError, StatfitError):
            pass
    return model.truncated(k) if k is not None else model


def open_model(path: str | Path | None, k: int | None = None) -> StatModel:
    """The model at ``path`` in any format (imported once and cached), or the embedded default
    when ``path`` is None; its first ``k`` modes."""
    return open_any_model(path, k=k) if path is not None else load_model(default_model_path(), k)
