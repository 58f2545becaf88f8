"""The API reference builds from the docstrings, one page per module (docs/api.py)."""
from __future__ import annotations

import runpy
from pathlib import Path

import pytest

pytest.importorskip("pdoc")


def test_api_reference_builds(tmp_path):
    api = runpy.run_path(str(Path(__file__).resolve().parents[1] / "docs" / "api.py"))
    api["build"](tmp_path)
    pages = {p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*.html")}
    assert {"statfit/core/methods.html", "statfit/core/fit.html", "statfit/core/parametrize.html",
            "statfit/registration/job.html"} <= pages
    assert "add_method" in (tmp_path / "statfit" / "core" / "methods.html").read_text()
