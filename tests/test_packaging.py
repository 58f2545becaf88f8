"""What a wheel ships: every package of the source tree, not only what an editable install finds.

An editable install resolves ``statfit.<anything>`` from the source folder, so a subpackage missing
from pyproject's list passes every other test and is left out of ``pip install .`` (``statfit.renderer``
was: ``statfit splat`` failed to import from a wheel).
"""
from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def listed_packages() -> tuple[set[str], dict[str, str]]:
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    return set(setuptools["packages"]), setuptools["package-dir"]


def test_every_package_folder_is_listed_for_the_wheel():
    packages, folders = listed_packages()
    for name, folder in folders.items():
        found = {name + "".join("." + part for part in init.parent.relative_to(ROOT / folder).parts)
                 for init in (ROOT / folder).rglob("__init__.py")}
        assert found, f"{folder}/ holds no package"
        missing = found - packages
        assert not missing, f"packages under {folder}/ that a wheel would leave out: {sorted(missing)}"


def test_every_listed_package_exists():
    packages, folders = listed_packages()
    for package in packages:
        top, *rest = package.split(".")
        assert (ROOT / folders[top] / Path(*rest) / "__init__.py").is_file(), package
