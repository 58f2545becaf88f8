#!/usr/bin/env python3
"""The suite on the oldest version of every dependency that pyproject.toml allows (issue 38, part 6).

    python .ci/oldest_deps.py VENV [PYTEST ARGS...]

Reads every requirement of ``[project] dependencies`` and of the ``test`` extra, pins each to its
lower bound (``>=X`` or ``==X`` becomes ``==X``), creates the virtual environment VENV (kept, so a
rerun only runs the tests), installs ``-e .[test]`` under those pins, prints what was installed and
runs ``python -m pytest`` there with PYTEST ARGS (default ``-q``). Exit status: pytest's, or 3 when
a requirement has no lower bound, or pip's when the pins cannot be installed (a bound that no
release on this Python satisfies is a bound to raise).

Not part of ``.ci/run`` (that is exactly the README's test command): run it when a bound changes.
docs/benchmarks.md records its last run.
"""
from __future__ import annotations

import re
import subprocess
import sys
import tomllib
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LOWER = re.compile(r"^\s*([A-Za-z0-9_.\-]+)(\[[^\]]*\])?\s*[^;]*?(?:>=|==)\s*([0-9][^,;\s]*)")


def lower_bounds(pyproject: Path) -> dict[str, str]:
    """{requirement name (with extras): its lowest allowed version} of the dependencies and the test extra."""
    project = tomllib.loads(pyproject.read_text())["project"]
    bounds = {}
    for requirement in [*project["dependencies"], *project["optional-dependencies"]["test"]]:
        match = LOWER.match(requirement)
        if match is None:
            sys.exit(f"oldest_deps: {requirement!r} has no lower bound to test")
        bounds[match.group(1) + (match.group(2) or "")] = match.group(3)
    return bounds


def main() -> int:
    if len(sys.argv) < 2 or sys.argv[1] in ("-h", "--help"):
        print(__doc__)
        return 0 if len(sys.argv) > 1 else 2
    folder = Path(sys.argv[1]).resolve()
    python = folder / "bin" / "python"
    if not python.is_file():
        venv.create(folder, with_pip=True)
        pins = folder / "oldest.txt"
        pins.write_text("".join(f"{name.split('[')[0]}=={version}\n" for name, version in lower_bounds(
            ROOT / "pyproject.toml").items()))
        installed = subprocess.run([str(python), "-m", "pip", "install", "-q", "-c", str(pins), "-e", f"{ROOT}[test]"])
        if installed.returncode:
            return installed.returncode
    subprocess.run([str(python), "-m", "pip", "list", "--format=freeze"], check=True)
    return subprocess.run([str(python), "-m", "pytest", *(sys.argv[2:] or ["-q"])], cwd=ROOT).returncode


if __name__ == "__main__":
    sys.exit(main())
