"""Model files: npz archives with reproducible bytes (fixed zip timestamps, no pickles), and reading them."""
from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np

from statfit.errors import StatfitError
from statfit.io.files import existing_file

# The most array data statfit reads from one npz (a 1024² RGB texture model of 100 modes is 1.2 GiB).
MAX_BYTES = 4 << 30


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """A compressed npz archive of ``arrays``, byte-identical for identical arrays; write it with
    ``statfit.io.files.write_atomic``."""
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
    path = existing_file(path, f"{what} file")
    if not zipfile.is_zipfile(path):
        raise StatfitError(f"cannot read {what} {path}: not an npz archive")
    try:
        check_npz_sizes(path, what)
        with np.load(path, allow_pickle=False) as data:
            return {key: data[key] for key in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise StatfitError(f"cannot read {what} {path}: {exc}") from None


def check_npz_sizes(path: Path, what: str) -> None:
    """Refuse, from the headers alone, an archive whose arrays would not fit: each member's .npy
    header must claim no more data than the member holds, and all together at most ``MAX_BYTES``."""
    total = 0
    with zipfile.ZipFile(path) as archive:
        for info in archive.infolist():
            with archive.open(info) as member:
                version = np.lib.format.read_magic(member)
                shape, _, dtype = (np.lib.format.read_array_header_1_0(member) if version == (1, 0)
                                   else np.lib.format.read_array_header_2_0(member))
                claimed = int(np.prod(shape, dtype=object)) * dtype.itemsize
            if claimed > info.file_size and not dtype.hasobject:  # object members are never loaded
                raise StatfitError(f"cannot read {what} {path}: {info.filename} claims {claimed:,} bytes of data "
                                   f"but holds {info.file_size:,}")
            total += info.file_size
    if total > MAX_BYTES:
        raise StatfitError(f"cannot read {what} {path}: its arrays take {total / 2**30:.1f} GiB, more than the "
                           f"{MAX_BYTES / 2**30:.0f} GiB statfit reads")
