"""Fits that stay finite but run away (a step size far too large: a fuzz of the CLI, 2026-11-28)
are refused in one line, exit 2 and nothing written, as a fit whose vertices stop being finite is;
a fit at the defaults is not."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from conftest import run_cli
from statfit.errors import DivergenceError
from statfit.core.runaway import RUNAWAY_IMAGE, check_not_runaway, image_ratio
from statfit.structures.camera import Camera


@pytest.fixture(scope="module")
def normal_map(tmp_path_factory):
    folder = tmp_path_factory.mktemp("runaway")
    normals, camera = folder / "n.exr", folder / "c.json"
    assert run_cli(["synth", "normals", "--size", "48", "--out", str(normals), "--camera-out", str(camera)])[0] == 0
    return normals, camera


def _refused_or_written(code: int, err: str, out, refused: bool, message: str) -> None:
    """Refused in one line naming ``message`` with nothing at ``out``, or written with exit 0."""
    if refused:
        assert code == 2 and err.count("\n") == 1 and message in err, (code, err)
        assert not out.exists()
    else:
        assert code == 0 and out.exists(), err


@pytest.mark.parametrize("lr, refused", [("1e6", True), ("10", True), (None, False)])
def test_a_render_fit_whose_image_outgrows_the_map_is_refused(normal_map, tmp_path, lr, refused):
    """`--lr 1e6` used to write a head 1e5 times too large with exit 0 (`--lr 10`: several times).
    Either of the runaway test's refusals: its image too large, or behind the camera (where an
    H200's `--lr 1e6` fit ended, its sums in another order)."""
    normals, camera = normal_map
    out = tmp_path / "fit.ply"
    code, err = run_cli(["render", str(normals), "--camera", str(camera), "--iterations", "40", "--out", str(out), "-q"]
                        + (["--lr", lr] if lr else []))
    _refused_or_written(code, err, out, refused, "the fit diverged: it")


def test_the_runaway_test_measures_the_image_against_the_silhouette_and_the_start():
    """A mesh scaled about its centre: refused at RUNAWAY_IMAGE times the silhouette and twice its
    start; a start already that large (a head fitted to a map of its face) lets it end there."""
    camera = Camera.look_at([0, 0, 3.0], [0, 0, 0], [0, 1, 0], 30.0, 64, 64)
    rng = np.random.default_rng(0)
    mesh = torch.as_tensor(rng.normal(scale=0.1, size=(200, 3)))
    mask = np.zeros((64, 64), bool)
    mask[20:44, 20:44] = True
    base = image_ratio(mesh, camera, mask)
    scale = 1.5 * RUNAWAY_IMAGE / base               # the image 1.5 × RUNAWAY_IMAGE times the silhouette
    check_not_runaway(mesh, mesh * 1.2, camera, mask)
    with pytest.raises(DivergenceError, match="its image is"):
        check_not_runaway(mesh, mesh * scale, camera, mask)
    check_not_runaway(mesh * scale * 0.8, mesh * scale, camera, mask)
    with pytest.raises(DivergenceError, match="behind the camera"):
        check_not_runaway(mesh, mesh + torch.tensor([0.0, 0.0, 10.0], dtype=torch.float64), camera, mask)


@pytest.mark.parametrize("lr, hole, refused", [("1e9", True, True), (None, True, False), (None, False, False)],
                         ids=["huge step", "default", "no hole"])
def test_an_inpainting_whose_colours_leave_the_image_range_is_refused(tmp_path, lr, hole, refused):
    """`--lr 1e9` used to fill a hole with ±1e6 (written as 0 and 255) with exit 0; an image without
    a hole has nothing to test (and is no divergence)."""
    from statfit.io.image import write_image

    rows, cols = np.mgrid[0:32, 0:32] / 31.0
    image = np.stack([rows, cols, 0.5 * (rows + cols)], axis=-1).astype(np.float32)
    visible = np.ones((32, 32, 1), np.float32)
    visible[10:20, 12:22] = 0.0 if hole else 1.0
    write_image(tmp_path / "image.png", image)
    write_image(tmp_path / "mask.png", visible)
    out = tmp_path / "filled.png"
    code, err = run_cli(["inpaint", str(tmp_path / "image.png"), "--mask", str(tmp_path / "mask.png"),
                         "--out", str(out), "-q"] + (["--lr", lr] if lr else []))
    _refused_or_written(code, err, out, refused, "the fill diverged")


def test_a_splat_fit_that_runs_away_is_refused(tmp_path):
    """`splat --lr 10` used to write a head 70 times its size with exit 0; tested against each
    training photograph's foreground."""
    views = tmp_path / "views"
    assert run_cli(["synth", "views", "--seed", "2", "--views", "4", "--size", "48", "--out", str(views)])[0] == 0
    for lr, refused in (("10", True), (None, False)):
        out = tmp_path / f"fit{lr}.ply"
        code, err = run_cli(["splat", str(views), "--iterations", "30", "--out", str(out), "-q"]
                            + (["--lr", lr] if lr else []))
        _refused_or_written(code, err, out, refused, "the fit diverged: it")
