"""The inputs a batch covers and the output each one gets: sub-folders mirrored under the output
folder, name clashes refused before any work."""
from __future__ import annotations

import glob
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

from statfit.errors import StatfitError

GLOB_CHARACTERS = frozenset("*?[")
STEM = "{stem}"     # in a companion-file template: the input's file name without its extension


@dataclass(frozen=True)
class Item:
    """One input (as named, and its absolute path: its identity in the manifest) and its output."""
    source: Path
    output: Path
    identity: str


def expand_inputs(patterns: list[str], exclude: Path | None = None) -> list[Path]:
    """The files named by ``patterns`` (paths, or globs where ``**`` spans folders), sorted, each
    once; files inside ``exclude`` (the output folder) are left out so a rerun never takes its
    own outputs as inputs."""
    found: dict[Path, None] = {}
    for pattern in patterns:
        if GLOB_CHARACTERS & set(pattern):
            matches = sorted(Path(p) for p in glob.glob(pattern, recursive=True) if os.path.isfile(p))
            if not matches:
                raise StatfitError(f"no file matches {pattern!r}")
        else:
            path = Path(pattern)
            if not path.is_file():
                raise StatfitError(f"input not found: {pattern}" if not path.exists() else f"input is not a file: {pattern}")
            matches = [path]
        for path in matches:
            found.setdefault(path, None)
    inputs = list(found)
    if exclude is not None:
        root = exclude.resolve()
        inputs = [p for p in inputs if not p.resolve().is_relative_to(root)]
        if not inputs:
            raise StatfitError(f"every input lies inside the output folder {exclude}")
    return inputs


def plan_outputs(inputs: list[Path], out_dir: Path, suffix: str = ".ply") -> list[Item]:
    """Each input's output: its path relative to the inputs' common folder, under ``out_dir``,
    with ``suffix``. Refuses two inputs with one output, and an output that is an input."""
    absolute = [p.resolve() for p in inputs]
    base = Path(os.path.commonpath([str(p.parent) for p in absolute]))
    items = [Item(p, out_dir / a.relative_to(base).with_suffix(suffix), str(a)) for p, a in zip(inputs, absolute)]
    owners: dict[str, Path] = {}
    out_root = out_dir.resolve()
    for item in items:
        key = os.path.normcase(str(out_root / item.output.relative_to(out_dir)))
        if key in owners:
            raise StatfitError(f"{owners[key]} and {item.source} would both be written to {item.output}; "
                               "rename one or run them as two batches")
        owners[key] = item.source
    sources = {os.path.normcase(item.identity) for item in items}
    for key, source in owners.items():
        if key in sources:
            raise StatfitError(f"the output for {source} would overwrite an input; choose another --out-dir")
    return items


def file_digest(path: Path) -> str:
    """sha256 of a file's bytes (read in 1 MiB blocks)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while block := handle.read(1 << 20):
            digest.update(block)
    return digest.hexdigest()


def check_companion_template(template: str, option: str) -> None:
    """Refuse, in one line, a ``template`` that does not name one file per input (no ``{stem}``)."""
    if STEM not in template:
        raise StatfitError(f"{option} names each scan's own file with {STEM}, the scan's name without its "
                           f"extension (e.g. '{STEM}.pts', beside each scan); got {template!r}")


def map_camera_file(camera: str | None, source: str | Path) -> str | None:
    """A render batch's ``camera`` option for the map ``source``: one file for every map, each map's
    own (a template with ``{stem}``: :func:`companion_file`), or None (the map's header)."""
    if camera is None or STEM not in camera:
        return camera
    return str(companion_file(Path(source), camera))


def companion_file(source: Path, template: str) -> Path:
    """The file ``template`` names for the input ``source``: ``{stem}`` replaced by its name without
    its extension; relative to the input's folder unless absolute (``{stem}.pts``: beside it)."""
    path = Path(template.replace(STEM, source.stem))
    return path if path.is_absolute() else source.parent / path
