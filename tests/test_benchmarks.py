"""The benchmark runner's parts complete on tiny sizes (CI checks that they run, not their timings)."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import filter_scaling  # noqa: E402
import inpainting  # noqa: E402
import run  # noqa: E402
from common import Section, machine  # noqa: E402


def test_filter_scaling_measures_every_solver_and_plots(tmp_path, monkeypatch):
    monkeypatch.setitem(filter_scaling.SIDES, "quick", (16, 32))
    monkeypatch.setitem(filter_scaling.KS, "quick", (4,))
    monkeypatch.setattr(filter_scaling, "BANDWIDTH_BYTES", 2**22)
    results = filter_scaling.measure(quick=True)
    from statfit.core.solvers import SOLVERS
    from statfit.core.threads import available_cores

    thread_counts = {1, available_cores()}
    assert {r["solver"] for r in results["laplacian"]} == set(SOLVERS)
    assert {r["threads"] for r in results["statistical"]} == thread_counts
    assert len(results["statistical"]) == 2 * len(thread_counts) and all(r["ms"] > 0 for r in results["statistical"])
    section = filter_scaling.section(results, tmp_path / "img")
    assert section.figures[0].stat().st_size > 0
    assert section.markdown.count("| 32 |") == len(thread_counts) + len(SOLVERS)


def test_inpainting_part_times_every_method(monkeypatch):
    monkeypatch.setattr(inpainting, "QUICK", {"size": 32, "k": 4, "iterations": 40})
    results = inpainting.measure(quick=True)
    assert [r["method"] for r in results["methods"]] == list(inpainting.METHODS)
    assert all(r["per_step_ms"] > 0 and 0 <= r["rmse"] < 1 for r in results["methods"])


def test_report_names_the_machine_and_numbers_the_sections():
    info = machine()
    text = run.report([Section("a", "First", "body one"), Section("b", "Second", "body two")], info, quick=True,
                      device="cpu", seconds=90.0)
    assert "## 1. First" in text and "## 2. Second" in text and "Quick mode" in text
    assert info["cpu"] in text and f"torch {info['torch']}" in text


def test_runner_refuses_unknown_parts(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["run.py", "--only", "nonsense"])
    with pytest.raises(SystemExit) as exit_info:
        run.main()
    assert exit_info.value.code == 2 and "unknown part" in capsys.readouterr().err


def test_render_ab_times_a_revisions_objective_beside_this_trees():
    """benchmarks/render_ab.py against HEAD: where the renderer and objective are HEAD's, the two
    objectives it times must give the same bits (its imports of the revision's modules work)."""
    import shutil
    import subprocess

    import render_ab

    root = Path(__file__).resolve().parents[1]
    if shutil.which("git") is None or subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"],
                                                      capture_output=True).returncode != 0:
        pytest.skip("not a git checkout git can read (none, or owned by another user)")
    result = render_ab.main(["--against", "HEAD", "--model", "embedded", "--size", "32", "--rounds", "2"])
    assert result["revision_modules"] == ("_rev_normals", "_rev_steady")    # the revision's, not this tree's
    assert all(len(values) == 2 and min(values) > 0 for values in result["times"].values())
    unchanged = subprocess.run(["git", "-C", str(root), "diff", "--quiet", "HEAD", "--", *render_ab.MODULES.values()])
    if unchanged.returncode == 0:
        assert result["same_bits"]


@pytest.mark.parametrize("option", [["--every", "0"], ["--rounds", "0"], ["--size", "4"]])
def test_render_ab_refuses_counts_that_measure_nothing(option, capsys):
    import render_ab

    with pytest.raises(SystemExit) as stopped:
        render_ab.main(option)
    assert stopped.value.code == 2 and "must be 1 or more" in capsys.readouterr().err
