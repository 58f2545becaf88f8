"""The MakeHuman data folder's layout (the CC0 ``makehuman`` data: base mesh, morph targets, vertex
groups) and the check that a folder has it, with the standard library only: a command checks the
folder before it loads the library, so a mistyped name is refused at once."""
from __future__ import annotations

from pathlib import Path

from statfit.errors import StatfitError

BASE_MESH = Path("3dobjs/base.obj.gz")
TARGETS = Path("targets")
SLIDERS = TARGETS / "target.json"
VERTEX_GROUPS = Path("mesh_metadata/basemesh_vertex_groups.json")
LAYOUT = (BASE_MESH, SLIDERS, VERTEX_GROUPS, TARGETS / "macrodetails")


def makehuman_folder(folder: str | Path) -> Path:
    """``folder`` as a Path when it holds every part of :data:`LAYOUT`; otherwise one line saying
    that it is not a folder, or which parts it lacks."""
    folder = Path(folder)
    if not folder.is_dir():
        raise StatfitError(f"{folder} is not a folder (expected the MakeHuman data folder: 3dobjs/, targets/, "
                           "mesh_metadata/)")
    missing = [str(part) for part in LAYOUT if not (folder / part).exists()]
    if missing:
        raise StatfitError(f"{folder} is not a MakeHuman data folder: it lacks {', '.join(missing)}")
    return folder
