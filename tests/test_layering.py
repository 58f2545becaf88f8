"""The house's layering, enforced: structures ← io ← model ← core ← jobs ← cli.

Each module may import from its own layer and the layers before it, never from a later one; the
core (the maths and the fitting loop) does not read or write files, so it never imports io.
"""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("structures", "io", "model", "core", "jobs", "cli")
# Module-name prefixes per layer; the longest matching prefix decides, and "core" is the rest of statfit.
PREFIXES = {
    "statfit.errors": "structures", "statfit.frame": "structures", "statfit.camera": "structures",
    "statfit.normal_map": "structures", "statfit.scan": "structures", "statfit.views": "structures",
    "statfit.io": "io",
    "statfit.model": "model", "statfit.pca": "model", "statfit.build": "model", "statfit.importers": "model",
    "statfit.texture.model": "model", "statfit.texture.resample": "model",
    "statfit.register": "jobs", "statfit.inverse_render": "jobs", "statfit.synth": "jobs", "statfit.scanner": "jobs",
    "statfit.preview": "jobs", "statfit.splatting": "jobs", "statfit.synth_views": "jobs",
    "statfit.splat_preview": "jobs",
    "statfit.texture.inpaint": "jobs", "statfit.texture.preview": "jobs", "statfit.batch": "jobs",
    "statfit_cli": "cli",
}


def layer(module: str) -> str:
    if module == "statfit":  # the package's front door re-exports the jobs
        return "jobs"
    matches = [p for p in PREFIXES if module == p or module.startswith(p + ".")]
    return PREFIXES[max(matches, key=len)] if matches else "core"


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


def test_no_module_imports_a_later_layer():
    broken = []
    for name, path in modules().items():
        own = LAYERS.index(layer(name))
        for imported in imports(path):
            if LAYERS.index(layer(imported)) > own:
                broken.append(f"{name} ({layer(name)}) imports {imported} ({layer(imported)})")
    assert not broken, "\n".join(broken)


def test_the_core_never_imports_io():
    broken = [f"{name} imports {imported}" for name, path in modules().items() if layer(name) == "core"
              for imported in imports(path) if layer(imported) == "io"]
    assert not broken, "\n".join(broken)


def test_the_library_never_imports_the_cli():
    broken = [name for name, path in modules().items() if name.startswith("statfit.")
              and any(i.startswith("statfit_cli") for i in imports(path))]
    assert not broken


def test_the_rule_catches_a_violation():
    assert LAYERS.index(layer("statfit.register")) > LAYERS.index(layer("statfit.filters"))
    assert layer("statfit.io.mesh") == "io" and layer("statfit.importers.cache") == "model"
