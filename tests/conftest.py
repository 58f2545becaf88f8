"""Shared fixtures: the embedded model, the real ICT model (../shared), small random problems.

``STATFIT_DEVICE=cuda python -m pytest`` runs every job the suite starts (register, render,
inpaint, batch, CLI) on the GPU: :func:`statfit.core.device.resolve_device` reads it."""
from __future__ import annotations

import multiprocessing
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest
import torch

from statfit.core.device import DEVICE_ENV
from statfit.model.statmodel import default_model_path, load_model

# The one definition of where the shared data lie, and of the ICT cases, is benchmarks/ (common.py, cases.py).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from common import ICT as ICT_DIR  # noqa: E402


# The test files that take longest (seconds on two workers, docs/benchmarks.md §16), longest first.
# The README's command gives each pytest-xdist worker whole files in collection order
# (``--dist loadfile --no-loadscope-reorder``): these start first and side by side, and the many short
# files fill in after, instead of a three-minute file starting last.
LONGEST_FIRST = ("test_bodies.py", "test_batch.py", "test_render_ict.py", "test_real_scans.py", "test_register_ict.py",
                 "test_fallback.py", "test_many_render.py", "test_fuzz_options.py", "test_other_models.py",
                 "test_cli.py", "test_held_out_half.py")


def pytest_collection_modifyitems(items):
    rank = {name: index for index, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(LONGEST_FIRST)))   # stable: files keep their order


def pytest_configure(config):
    if os.environ.get(DEVICE_ENV, "").startswith("cuda") and not torch.cuda.is_available():
        raise pytest.UsageError(f"{DEVICE_ENV}={os.environ[DEVICE_ENV]} but torch sees no CUDA device")


@pytest.fixture(scope="session")
def embedded_model():
    return load_model(default_model_path())


@pytest.fixture(scope="session")
def ict_model():
    path = ICT_DIR / "ict_face_identity.npz"
    if not path.is_file():
        pytest.skip(f"ICT data not found at {path}")
    return load_model(path)


def normal_map_scene(model, size: int) -> tuple:
    """A normal map (size², of one sample of ``model``, seed 3, yaw 20°, pitch 5°) and its camera."""
    from statfit.renderer.images import render_target
    from statfit.structures.normal_map import NormalMap
    from statfit.synth.sample import camera_for_view

    shape = model.sample(np.random.default_rng(3), 1.0)
    camera = camera_for_view(shape, 20.0, 5.0, size)
    return NormalMap(*render_target(shape, model.faces, camera)), camera


def run_two_at_a_time(job: Callable[..., Any], arguments: dict[str, tuple]) -> dict[str, Any]:
    """``{name: job(*args)}``, two jobs at a time in fresh processes (spawned: no torch state
    shared with the test process). Long single-threaded fits gain little from a second thread, so
    this halves the wall time on a 2-core machine; ``job`` sets its own thread count."""
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {name: pool.submit(job, *args) for name, args in arguments.items()}
        return {name: future.result() for name, future in futures.items()}


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture(autouse=True)
def _threads():
    """Two torch threads a test process, one a worker where pytest-xdist runs two or more: the
    README's two workers on CI's two cores, two threads each, oversubscribe the cores, and OpenMP's
    threads spin waiting for each other (two heavy test files on two workers: 316 s, 219 s with
    one thread a worker; docs/benchmarks.md §16)."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    torch.set_num_threads(max(1, 2 // workers))


@pytest.fixture(scope="module")
def scan_files(tmp_path_factory) -> tuple[Path, Path]:
    """``statfit synth scan --seed 3``'s scan and ground truth (the CLI tests' input), made once a file."""
    from statfit_cli.main import main

    folder = tmp_path_factory.mktemp("scan")
    with pytest.raises(SystemExit) as exit_info:
        main(["synth", "scan", "--seed", "3", "--out", str(folder / "scan.ply"), "--gt", str(folder / "gt.ply")])
    assert exit_info.value.code == 0
    return folder / "scan.ply", folder / "gt.ply"


def run_cli(argv: list[str]) -> tuple[int, str]:
    """Run ``statfit argv`` in this process: (exit code, stderr); stdout is discarded."""
    import contextlib
    import io

    from statfit_cli.main import main

    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        try:
            main(argv)
            code = 0
        except SystemExit as exit_info:
            code = exit_info.code if isinstance(exit_info.code, int) else 1
    return code, err.getvalue()
