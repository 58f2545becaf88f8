"""The house's layering, enforced by folder: each folder of ``statfit/`` is one layer.

    structures ← renderer ← geometry ← io ← model ← core ← jobs ← batch ← cli

A module may import from its own layer and the layers before it, never from a later one. Within
the jobs layer each job is its own room: a job never imports another job (what two jobs share
lives below them). The core and the geometry do not read or write files, so they never import io;
nothing in the library imports the CLI.
"""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("structures", "renderer", "geometry", "io", "model", "core", "jobs", "batch", "cli")
# Top-level names of statfit/ and the layer each one is.
FOLDERS = {
    "errors": "structures", "structures": "structures",
    "renderer": "renderer",
    "geometry": "geometry",
    "io": "io",
    "model": "model",
    "core": "core", "objectives": "core",
    "registration": "jobs", "render": "jobs", "splat": "jobs", "synth": "jobs", "texture": "jobs",
    "batch": "batch",
}
JOBS = {name for name, kind in FOLDERS.items() if kind == "jobs"}


def room(module: str) -> str:
    """The top-level folder (or module) of statfit a module lives in; 'cli' for the CLI, '' for the
    package's front door."""
    if module.startswith("statfit_cli"):
        return "cli"
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def layer(module: str) -> str:
    if module == "statfit":  # the package's front door re-exports the jobs
        return "batch"
    name = room(module)
    return "cli" if name == "cli" else FOLDERS[name]


def modules() -> dict[str, Path]:
    found = {}
    for package, folder in (("statfit", ROOT / "statfit"), ("statfit_cli", ROOT / "cli")):
        for path in folder.rglob("*.py"):
            parts = path.relative_to(folder).with_suffix("").parts
            name = ".".join((package, *parts)).removesuffix(".__init__")
            found[name] = path
    return found


def imports(path: Path) -> set[str]:
    """Every statfit module a file imports, at any depth (function-local imports too)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
    return {n for n in names if n.split(".")[0] in ("statfit", "statfit_cli")}


def test_every_folder_of_the_library_has_a_layer():
    tops = {p.stem for p in (ROOT / "statfit").iterdir()
            if (p.is_dir() and (p / "__init__.py").exists()) or (p.suffix == ".py" and p.stem != "__init__")}
    assert tops == set(FOLDERS), f"unplaced: {sorted(tops - set(FOLDERS))}, gone: {sorted(set(FOLDERS) - tops)}"


def test_no_module_imports_a_later_layer():
    broken = []
    for name, path in modules().items():
        own = LAYERS.index(layer(name))
        for imported in imports(path):
            if LAYERS.index(layer(imported)) > own:
                broken.append(f"{name} ({layer(name)}) imports {imported} ({layer(imported)})")
    assert not broken, "\n".join(broken)


def test_a_job_never_imports_another_job():
    broken = [f"{name} imports {imported}" for name, path in modules().items() if room(name) in JOBS
              for imported in imports(path) if room(imported) in JOBS and room(imported) != room(name)]
    assert not broken, "\n".join(broken)


def test_the_core_and_geometry_never_import_io():
    broken = [f"{name} imports {imported}" for name, path in modules().items()
              if layer(name) in ("core", "geometry", "renderer") for imported in imports(path) if layer(imported) == "io"]
    assert not broken, "\n".join(broken)


def test_the_library_never_imports_the_cli():
    broken = [name for name, path in modules().items() if name.startswith("statfit.")
              and any(i.startswith("statfit_cli") for i in imports(path))]
    assert not broken


def test_the_rules_catch_a_violation():
    assert LAYERS.index(layer("statfit.registration.job")) > LAYERS.index(layer("statfit.core.filters"))
    assert layer("statfit.io.mesh") == "io" and layer("statfit.model.importers.cache") == "model"
    assert room("statfit.render.job") != room("statfit.renderer.raster")
    assert room("statfit.render.job") in JOBS and room("statfit.renderer.raster") not in JOBS


def test_no_module_is_over_350_lines():
    long = {name: n for name, path in modules().items() if (n := len(path.read_text().splitlines())) > 350}
    assert not long, long
