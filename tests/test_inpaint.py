"""Texture inpainting: the grid Laplacian and the filters on a grid against dense closed forms,
image I/O round trips, texture models, and the issue's accuracy claims on scikit-learn's digits and
the generated face textures (hybrid beats the Laplacian at λ = 99 and 999 on the hole pixels)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from statfit.errors import StatfitError
from statfit.core.filters import HybridFilter, LaplacianFilter
from statfit.io.image import read_charts, read_image, read_mask, write_image
from statfit.texture.grid import grid_laplacian
from statfit.texture.inpaint import inpaint, inpaint_settings, model_reconstruction
from statfit.texture.model import (as_channels, build_texture_model, jitter_colours, load_texture_model,
                                   texture_model_from_arrays)
from statfit.texture.resample import resize_image
from texture_fixtures import brow_hole, face_textures, hole_errors


@pytest.fixture(autouse=True)
def _threads():
    """One thread (overrides conftest's two): these images are small, and on a shared 2-core
    machine a second thread makes each step wait for the other processes."""
    torch.set_num_threads(1)


def dense_grid_laplacian(height: int, width: int, labels: np.ndarray | None = None) -> np.ndarray:
    """Brute force: every pair of pixels one step apart, kept when both lie in the same chart."""
    n = height * width
    adjacency = np.zeros((n, n))
    for a in range(n):
        for b in range(n):
            (ia, ja), (ib, jb) = divmod(a, width), divmod(b, width)
            if abs(ia - ib) + abs(ja - jb) == 1 and (labels is None or labels[ia, ja] == labels[ib, jb] != 0):
                adjacency[a, b] = 1.0
    return np.diag(adjacency.sum(axis=1)) - adjacency


def test_grid_laplacian_matches_the_brute_force_build():
    got = grid_laplacian(4, 5).toarray()
    np.testing.assert_array_equal(got, dense_grid_laplacian(4, 5))
    np.testing.assert_array_equal(got.sum(axis=1), 0.0)
    assert got[0, 0] == 2 and got[6, 6] == 4          # a corner has 2 neighbours, an inner pixel 4


def test_chart_restriction_removes_every_edge_leaving_a_chart():
    labels = np.array([[1, 1, 2, 2, 0], [1, 1, 2, 2, 0], [3, 3, 3, 0, 0], [3, 3, 3, 0, 0]])
    got = grid_laplacian(4, 5, labels).toarray()
    np.testing.assert_array_equal(got, dense_grid_laplacian(4, 5, labels))
    np.testing.assert_array_equal(got.sum(axis=1), 0.0)
    flat = labels.reshape(-1)
    rows, cols = np.nonzero(got)
    assert (flat[rows] == flat[cols]).all()               # no edge between charts
    assert not got[flat == 0].any()                       # gutter pixels have no edges
    with pytest.raises(StatfitError, match="chart image is 5×4 but the texture is 4×4"):
        grid_laplacian(4, 4, labels)


def test_hybrid_filter_on_a_grid_equals_the_dense_closed_form(rng):
    height, width, channels, k, beta, lam = 4, 5, 3, 4, 30.0, 19.0
    n = height * width * channels
    u, _ = np.linalg.qr(rng.standard_normal((n, k)))
    smooth = LaplacianFilter.from_laplacian(grid_laplacian(height, width), lam, dtype=torch.float64)
    hybrid = HybridFilter(torch.as_tensor(u.T), beta, smooth)
    g = rng.standard_normal((height * width, channels))
    # Entry p·C + c of the flattened image is channel c of pixel p: the Laplacian acts per channel.
    laplacian = np.kron(dense_grid_laplacian(height, width), np.eye(channels))
    alpha = beta / (1 + beta)
    dense = alpha * u @ u.T + (1 - alpha) * np.linalg.inv(np.eye(n) + lam * laplacian)
    got = hybrid(torch.as_tensor(g)).numpy().reshape(-1)
    np.testing.assert_allclose(got, dense @ g.reshape(-1), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_png_round_trip_is_exact_in_8_bit(tmp_path, rng, channels):
    image = rng.integers(0, 256, (6, 7, channels)).astype(np.float32) / 255.0
    write_image(tmp_path / "a.png", image)
    back = read_image(tmp_path / "a.png")
    assert back.shape == (6, 7, channels) and back.dtype == np.float32
    np.testing.assert_array_equal(back, image)


def test_exr_round_trip_keeps_floats_and_other_formats_read(tmp_path, rng):
    image = rng.uniform(-0.5, 2.0, (5, 4, 3)).astype(np.float32)       # EXR is not clipped
    write_image(tmp_path / "a.exr", image)
    np.testing.assert_array_equal(read_image(tmp_path / "a.exr"), image)
    Image.fromarray((rng.integers(0, 65536, (5, 4))).astype(np.uint16)).save(tmp_path / "deep.png")
    deep = read_image(tmp_path / "deep.png")
    assert deep.shape == (5, 4, 1) and 0 <= deep.min() and deep.max() <= 1
    smooth = np.broadcast_to(np.linspace(0, 1, 32)[None, :, None], (16, 32, 3)).astype(np.float32)
    write_image(tmp_path / "a.jpg", smooth)
    assert np.abs(read_image(tmp_path / "a.jpg") - smooth).max() < 0.03
    with pytest.raises(StatfitError, match="unsupported image format"):
        write_image(tmp_path / "a.bmp", smooth)


def test_masks_and_charts_from_images(tmp_path):
    grey = np.array([[0, 127, 128, 255]], dtype=np.uint8)
    Image.fromarray(grey).save(tmp_path / "m.png")
    np.testing.assert_array_equal(read_mask(tmp_path / "m.png"), [[False, False, True, True]])
    colours = np.array([[[0, 0, 0], [255, 0, 0], [255, 0, 0], [0, 0, 255]]], dtype=np.uint8)
    Image.fromarray(colours).save(tmp_path / "c.png")
    labels = read_charts(tmp_path / "c.png")
    assert labels[0, 0] == 0 and labels[0, 1] == labels[0, 2] != 0 and labels[0, 3] not in (0, labels[0, 1])


def test_8_bit_and_float_inputs_of_one_image_fill_alike(tmp_path):
    truth = face_textures(1, 32, seed=5)[0]
    write_image(tmp_path / "t.png", truth)
    write_image(tmp_path / "t.exr", truth)
    visible = brow_hole(32)
    filled = [inpaint(read_image(tmp_path / name), visible, "laplacian").result for name in ("t.png", "t.exr")]
    assert np.abs(filled[0] - filled[1]).max() < 2 / 255


@pytest.fixture(scope="module")
def faces():
    """A model (K = 40) of 150 generated 64×64 faces, and 4 held-out faces."""
    train = face_textures(150, 64, seed=1)
    model = build_texture_model([(str(i), t) for i, t in enumerate(train)], (64, 64), 40)
    return model, face_textures(4, 64, seed=99)


def test_texture_model_npz_round_trip_and_any_scale_directions(faces, tmp_path, rng):
    model, _ = faces
    model.save(tmp_path / "m.npz")
    loaded = load_texture_model(tmp_path / "m.npz")
    assert loaded.size == (64, 64) and loaded.channels == 3 and loaded.num_modes == 40
    np.testing.assert_allclose(loaded.std, model.std, rtol=1e-5)
    np.testing.assert_allclose(loaded.basis_t @ loaded.basis_t.T, np.eye(40), atol=1e-4)
    coeffs = rng.standard_normal(40)
    np.testing.assert_allclose(loaded.texture(coeffs), model.texture(coeffs), atol=1e-4)
    # Directions mixed by an invertible K × K matrix span the same space: the derived basis spans it too.
    arrays = model.npz_arrays()
    mixed = arrays["shapedirs"] @ rng.standard_normal((40, 40))
    other = texture_model_from_arrays(arrays["v_template"], mixed, arrays["image_size"])
    projected = other.basis_t.T @ (other.basis_t @ model.basis_t.T)     # UUᵀ applied to the original basis
    np.testing.assert_allclose(projected, model.basis_t.T, atol=1e-3)


def test_jitter_changes_colours_within_range_and_keeps_alpha(rng):
    images = rng.uniform(0, 1, (2, 4, 4, 4)).astype(np.float32)
    jittered = jitter_colours(images, 3, rng)
    assert jittered.shape == (6, 4, 4, 4) and 0 <= jittered.min() and jittered.max() <= 1
    np.testing.assert_array_equal(jittered[..., 3], np.repeat(images[..., 3], 3, axis=0))
    assert np.abs(jittered[:3, ..., :3] - images[:1, ..., :3]).mean() > 0.01
    assert as_channels(images[0, ..., :1], 3, "x").shape == (4, 4, 3)
    with pytest.raises(StatfitError, match="has 4 channel"):
        as_channels(images[0], 3, "x")


def test_model_reconstruction_recovers_a_texture_in_the_model(faces, rng):
    model, _ = faces
    truth = model.texture(rng.standard_normal(model.num_modes))
    visible = brow_hole(64)
    got = model_reconstruction(model, truth, visible)
    assert hole_errors(got, truth, visible)["rmse"] < 0.01


def test_visible_pixels_are_kept_and_resize_fits_at_the_model_size(faces):
    model, tests = faces
    visible = brow_hole(64)
    result = inpaint(tests[0], visible, "hybrid", model, settings=inpaint_settings("hybrid", iterations=30)).result
    np.testing.assert_array_equal(result[visible], tests[0][visible])
    large, large_visible = resize_image(tests[0], (96, 96)), brow_hole(96)
    with pytest.raises(StatfitError, match="model is 64×64 but the image is 96×96; pass --resize"):
        inpaint(large, large_visible, "hybrid", model)
    resized = inpaint(large, large_visible, "hybrid", model, resize=True,
                      settings=inpaint_settings("hybrid", iterations=30))
    assert resized.result.shape == (96, 96, 3) and resized.model_only.shape == (96, 96, 3)
    np.testing.assert_array_equal(resized.result[large_visible], large[large_visible])


def test_charts_stop_colour_bleeding_across_a_border():
    image = np.zeros((16, 16, 3), np.float32)
    image[:, :8, 0] = 1.0                                   # left chart red, right chart blue
    image[:, 8:, 2] = 1.0
    visible = np.ones((16, 16), bool)
    visible[4:12, 4:8] = False                              # a hole in the red chart, touching the border
    charts = np.where(np.arange(16) < 8, 1, 2)[None, :].repeat(16, axis=0)
    settings = inpaint_settings("laplacian", iterations=200, lam=99.0)
    bled = inpaint(image, visible, "laplacian", settings=settings).result
    kept = inpaint(image, visible, "laplacian", settings=settings, charts=charts).result
    hole = ~visible
    assert bled[hole][:, 2].max() > 0.1                     # without charts blue diffuses into the hole
    assert kept[hole][:, 2].max() < 0.02 and kept[hole][:, 0].min() > 0.9


def compare(model, tests, visible) -> dict[str, np.ndarray]:
    """Mean hole RMSE and correlation per method over ``tests``."""
    runs = {"hybrid": ("hybrid", model, {}), "laplacian 99": ("laplacian", None, {"lam": 99.0}),
            "laplacian 999": ("laplacian", None, {"lam": 999.0})}
    scores = {}
    for name, (method, use_model, overrides) in runs.items():
        settings = inpaint_settings(method, **overrides)
        errors = [hole_errors(inpaint(t, visible, method, use_model, settings=settings).result, t, visible)
                  for t in tests]
        scores[name] = np.array([[e["rmse"], e["correlation"]] for e in errors]).mean(axis=0)
    return scores


def assert_hybrid_wins(scores: dict[str, np.ndarray], margin: float) -> None:
    for baseline in ("laplacian 99", "laplacian 999"):
        assert scores["hybrid"][0] < (1 - margin) * scores[baseline][0], scores
        assert scores["hybrid"][1] > scores[baseline][1] + margin, scores


def test_hybrid_beats_laplacian_on_generated_faces_with_a_brow_hole(faces):
    model, tests = faces
    scores = compare(model, tests, brow_hole(64))
    assert_hybrid_wins(scores, 0.3)


def test_hybrid_beats_laplacian_on_sklearn_digits_with_a_central_hole():
    from sklearn.datasets import load_digits

    # 8×8 digits upscaled to 32×32: at 8×8 a hole leaves too few pixels for diffusion to matter.
    digits = load_digits().images.astype(np.float32) / 16.0
    # All 1,797 digits resampled at once, as the channels of one image.
    images = resize_image(digits.transpose(1, 2, 0), (32, 32)).transpose(2, 0, 1)[..., None]
    model = build_texture_model([(str(i), d) for i, d in enumerate(images[8:])], (32, 32), 30)
    visible = np.ones((32, 32), bool)
    visible[8:24, 8:24] = False                               # the central quarter of the image
    scores = compare(model, images[:8], visible)
    assert_hybrid_wins(scores, 0.3)
