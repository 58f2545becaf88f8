"""Model files: npz archives with reproducible bytes (fixed zip timestamps, no pickles), and reading them."""
from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np

from statfit.errors import StatfitError


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """A compressed npz archive of ``arrays``, byte-identical for identical arrays; write it with
    ``statfit.io.mesh.write_atomic``."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, array in arrays.items():
            member = io.BytesIO()
            np.lib.format.write_array(member, np.ascontiguousarray(array), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            archive.writestr(info, member.getvalue())
    return buffer.getvalue()


def read_npz(path: str | Path, what: str = "model") -> dict[str, np.ndarray]:
    """All arrays of the npz archive at ``path`` (no pickles); ``what`` names it in messages."""
    path = Path(path)
    if not path.is_file():
        raise StatfitError(f"{what} file not found: {path}")
    if not zipfile.is_zipfile(path):
        raise StatfitError(f"cannot read {what} {path}: not an npz archive")
    try:
        with np.load(path, allow_pickle=False) as data:
            return {key: data[key] for key in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise StatfitError(f"cannot read {what} {path}: {exc}") from None
