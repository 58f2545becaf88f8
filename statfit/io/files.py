"""Files by path, before and after any work: the check every reader makes first, the checks of an
output path made before a fit starts, and the atomic write every writer makes (``-`` is stdout).

Nothing here imports more than the standard library: a command checks its paths before it loads
the library, so a mistyped name is refused at once."""
from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

from statfit.errors import StatfitError

PARAMS_SUFFIXES = (".json", ".npz")
# Text point clouds (statfit.io.point_text), read and written.
POINT_TEXT_SUFFIXES = (".xyz", ".asc", ".csv", ".txt")


def existing_file(path: str | Path, what: str) -> Path:
    """``path`` as a Path when it names a readable file; otherwise one message saying whether it
    is missing, a folder, or too long a name (``what`` names the file: "scan", "camera file")."""
    path = Path(path)
    try:
        if path.is_dir():
            raise StatfitError(f"{what} {path} is a folder, not a file")
        if not path.is_file():
            raise StatfitError(f"{what} not found: {path}")
    except OSError as exc:  # e.g. a name longer than the system allows
        raise StatfitError(f"{what} {str(path)[:80]}…: {exc.strerror}") from None
    return path


def existing_folder(path: str | Path, what: str) -> Path:
    """``path`` as a Path when it names a folder; otherwise one message saying whether it is
    missing or not a folder (``what`` names the folder: "views folder")."""
    path = Path(path)
    if not path.is_dir():
        raise StatfitError(f"{what} {'is not a folder' if path.exists() else 'not found'}: {path}")
    return path


def _umask() -> int:
    """The process's umask (read by setting it and putting it back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_atomic(target: str | Path, data: bytes) -> None:
    """Write ``data`` to ``target`` via a temporary file in the same folder and a rename, so a
    reader never sees a half-written file; ``-`` writes to stdout."""
    if str(target) == "-":
        sys.stdout.buffer.write(data)
        sys.stdout.buffer.flush()
        return
    path = Path(target)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise StatfitError(f"output folder does not exist: {folder}")
    try:
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".statfit-", suffix=".tmp")  # short: any legal name fits
    except OSError as exc:
        raise StatfitError(f"cannot write to {folder}: {exc.strerror}") from None
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; a plain write would honour the umask
        os.replace(tmp, path)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        raise StatfitError(f"cannot write {path}: {exc.strerror}") from None


def mesh_format(target: str | Path) -> str:
    """``obj`` for a .obj path, else ``ply`` (a .ply path, one without a suffix, stdout); a path with
    another suffix is refused (PLY bytes in a file named .stl open nowhere)."""
    suffix = "" if str(target) == "-" else Path(str(target)).suffix.lower()
    if suffix not in ("", ".ply", ".obj"):
        raise StatfitError(f"{target}: meshes are written as .ply or .obj, not {suffix}")
    return "obj" if suffix == ".obj" else "ply"


def points_format(target: str | Path) -> str:
    """``text`` for a text point cloud's path (:data:`POINT_TEXT_SUFFIXES`), else ``ply`` (a .ply
    path, one without a suffix, stdout); a path with another suffix is refused."""
    suffix = "" if str(target) == "-" else Path(str(target)).suffix.lower()
    if suffix in POINT_TEXT_SUFFIXES:
        return "text"
    if suffix not in ("", ".ply"):
        raise StatfitError(f"{target}: point clouds are written as .ply or as text ({', '.join(POINT_TEXT_SUFFIXES)}), "
                           f"not {suffix}")
    return "ply"


def check_writable(target: str | Path) -> None:
    """Fail early, before any work, if ``target`` cannot be written: its folder is missing or not
    writable, it is a folder, or its name is too long — tried by creating (and removing) a file
    beside it, which also catches folders that refuse new files (/proc, a read-only mount)."""
    if str(target) == "-":
        return
    path = Path(target)
    folder = path.parent if str(path.parent) else Path(".")
    try:
        if not folder.is_dir():
            raise StatfitError(f"output folder does not exist: {folder}")
        if path.is_dir():
            raise StatfitError(f"output path is a folder: {target}")
        name_limit = os.pathconf(folder, "PC_NAME_MAX")
        if len(os.fsencode(path.name)) > name_limit:
            raise StatfitError(f"output name is longer than the {name_limit} bytes this file system allows: "
                               f"{path.name[:40]}…")
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".statfit-", suffix=".tmp"):
            pass
    except StatfitError:
        raise
    except OSError as exc:
        raise StatfitError(f"cannot write {str(path)[:200]}: {exc.strerror}") from None


def output_suffix(target: str | Path, suffixes: tuple[str, ...], what: str) -> None:
    """Refuse, before any work, an output path whose suffix is none of ``suffixes`` (its bytes
    would open nowhere under that name); ``what`` names the file ("a model")."""
    suffix = Path(str(target)).suffix.lower()
    if suffix not in suffixes:
        raise StatfitError(f"{target}: {what} is written as {' or '.join(suffixes)}, not "
                           f"{suffix or 'a name without a suffix'}")


def params_suffix(path: str | Path) -> str:
    """A params file's suffix (statfit.model.params_file): ``.json`` or ``.npz``; anything else refused
    before any work."""
    suffix = Path(str(path)).suffix.lower()
    if suffix not in PARAMS_SUFFIXES:
        raise StatfitError(f"--params {path}: the file must end in .json or .npz")
    return suffix
