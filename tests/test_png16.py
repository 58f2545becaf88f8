"""16-bit colour PNGs (textures, normal maps) read at all their 16 bits, not Pillow's 8."""
from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh
from PIL import Image

from png_files import png_bytes
from statfit.io.image import read_image
from statfit.io.normalmap import read_normal_map


@pytest.mark.parametrize("channels", [3, 4])
@pytest.mark.parametrize("interlaced", [False, True])
def test_the_png_writer_of_these_tests_is_read_by_pillow_as_written(channels, interlaced):
    """8-bit files of the tests' own writer (every filter type, Adam7) decode to what was written:
    the writer's 16-bit files are then what the specification says."""
    samples = np.random.default_rng(channels).integers(0, 256, (23, 17, channels), dtype=np.uint8)
    with Image.open(io.BytesIO(png_bytes(samples, interlaced))) as image:
        np.testing.assert_array_equal(np.asarray(image), samples)


@pytest.mark.parametrize("channels", [3, 4])
@pytest.mark.parametrize("interlaced", [False, True])
def test_a_16_bit_colour_png_reads_at_16_bits(tmp_path, channels, interlaced):
    """Every sample exact (v / 65535), whatever the scanlines' filters; Pillow alone keeps the high
    byte, 1 in 256 of these values."""
    samples = np.random.default_rng(7).integers(0, 65536, (23, 17, channels), dtype=np.uint16)
    path = tmp_path / "t.png"
    path.write_bytes(png_bytes(samples, interlaced))
    image = read_image(path)
    assert image.dtype == np.float32 and image.shape == samples.shape
    np.testing.assert_array_equal(np.round(image * 65535.0).astype(np.uint16), samples)


def _normals(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals of a sphere's cap (size, size, 3) and its mask."""
    u = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    x, y = np.meshgrid(u, u)
    mask = x * x + y * y < 0.9
    normals = np.stack([x, y, np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, None))], axis=-1)
    return normals * mask[..., None], mask


def test_a_16_bit_png_normal_map_keeps_its_precision(tmp_path):
    """Normals within 1e-4 of those encoded (8 bits: ~4e-3), the mask from alpha."""
    normals, mask = _normals(64)
    encoded = np.round((normals + 1.0) / 2.0 * 65535.0).astype(np.uint16)
    alpha = (mask * 65535).astype(np.uint16)[..., None]
    path = tmp_path / "n.png"
    path.write_bytes(png_bytes(np.concatenate([encoded, alpha], axis=-1), interlaced=True))
    loaded = read_normal_map(path)
    np.testing.assert_array_equal(loaded.mask, mask)
    assert np.abs(loaded.normals - normals)[mask].max() < 1e-4


def test_render_fits_a_16_bit_png_as_an_exr_of_its_16_bit_values(tmp_path, capsys):
    """`statfit render` of a 16-bit PNG map gives the mesh it gives for an EXR holding the PNG's
    values decoded here ((v / 65535) · 2 − 1, float32): all 16 bits reach the fit (8 of them would
    move it by far more)."""
    from test_cli import run
    from statfit.io.normalmap import write_normal_map

    exr, camera, gt = tmp_path / "n.exr", tmp_path / "cam.json", tmp_path / "gt.ply"
    assert run(["synth", "normals", "--seed", "3", "--size", "96", "--out", str(exr), "--camera-out", str(camera),
                "--gt", str(gt)], capsys)[0] == 0
    exact = read_normal_map(exr)
    encoded = np.where(exact.mask[..., None], np.round((exact.normals + 1.0) / 2.0 * 65535.0), 0).astype(np.uint16)
    png, decoded = tmp_path / "n.png", tmp_path / "decoded.exr"
    png.write_bytes(png_bytes(encoded))
    normals = (encoded.astype(np.float32) / np.float32(65535.0)) * np.float32(2.0) - np.float32(1.0)
    write_normal_map(decoded, normals * exact.mask[..., None], exact.mask)
    fits = []
    for source in (png, decoded):
        fit = tmp_path / f"{source.stem}_fit.ply"
        code, _, err = run(["render", str(source), "--camera", str(camera), "--out", str(fit), "--iterations", "60",
                            "-q"], capsys)
        assert code == 0, err
        fits.append(trimesh.load(fit, process=False).vertices)
    np.testing.assert_allclose(fits[0], fits[1], rtol=0, atol=1e-6 * np.ptp(fits[1], axis=0).max())


def test_a_cut_16_bit_png_is_refused_in_one_line(tmp_path, capsys):
    """Its second decode reads the same damaged data: one line, exit 2, as an 8-bit file's."""
    from test_cli import run
    from statfit.io.normalmap import write_camera
    from statfit.structures.camera import Camera

    normals, mask = _normals(64)
    encoded = np.round((normals + 1.0) / 2.0 * 65535.0).astype(np.uint16)
    whole = png_bytes(np.concatenate([encoded, (mask * 65535).astype(np.uint16)[..., None]], axis=-1))
    path, camera = tmp_path / "n.png", tmp_path / "cam.json"
    path.write_bytes(whole[: len(whole) // 2])
    write_camera(camera, Camera.look_at([0, 0, 50], [0, 0, 0], [0, 1, 0], 30.0, 64, 64))
    code, _, err = run(["render", str(path), "--camera", str(camera), "--out", str(tmp_path / "f.ply")], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "n.png" in err, err
    assert not (tmp_path / "f.ply").exists()


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_statfits_16_bit_png_writer_is_read_as_written(tmp_path, channels):
    """Pillow writes no 16-bit colour PNG; statfit's own writer (statfit.io.image.png16_bytes): Pillow
    opens its files as the right mode and reads the high bytes, statfit's reader every sample."""
    from statfit.io.image import png16_bytes, sample_bits

    samples = np.random.default_rng(channels).integers(0, 65536, (23, 17, channels), dtype=np.uint16)
    path = tmp_path / "t.png"
    path.write_bytes(png16_bytes(samples))
    with Image.open(path) as image:
        assert image.mode == {1: "I;16", 3: "RGB", 4: "RGBA"}[channels] and image.size == (17, 23)
        if channels > 1:
            np.testing.assert_array_equal(np.asarray(image), samples >> 8)
    np.testing.assert_array_equal(np.round(read_image(path) * 65535.0).astype(np.uint16), samples)
    assert sample_bits(path) == 16


def test_inpaint_of_a_16_bit_png_writes_16_bits(tmp_path, capsys):
    """`statfit inpaint` keeps a 16-bit input's precision in a PNG out: its visible pixels come back
    to the sample (8 bits would round them by up to 128 steps of 65,535); an 8-bit input still gives
    an 8-bit PNG."""
    from test_cli import run
    from statfit.io.image import sample_bits

    rng = np.random.default_rng(5)
    u = np.linspace(0.0, 1.0, 40)
    smooth = np.stack([np.outer(u, u), np.outer(u, 1 - u), np.outer(1 - u, u)], axis=-1)
    samples = np.round(smooth * 60000 + rng.integers(0, 256, smooth.shape)).astype(np.uint16)
    image, mask = tmp_path / "t16.png", tmp_path / "mask.png"
    image.write_bytes(png_bytes(samples))
    visible = np.ones((40, 40), dtype=bool)
    visible[12:20, 15:25] = False
    Image.fromarray((visible * 255).astype(np.uint8)).save(mask)
    code, _, err = run(["inpaint", str(image), "--mask", str(mask), "--iterations", "50", "-q", "--out",
                        str(tmp_path / "out16.png")], capsys)
    assert code == 0, err
    assert sample_bits(tmp_path / "out16.png") == 16
    filled = np.round(read_image(tmp_path / "out16.png") * 65535.0).astype(np.int64)
    np.testing.assert_array_equal(filled[visible], samples[visible])
    Image.fromarray((samples >> 8).astype(np.uint8)).save(tmp_path / "t8.png")
    code, _, err = run(["inpaint", str(tmp_path / "t8.png"), "--mask", str(mask), "--iterations", "50", "-q",
                        "--out", str(tmp_path / "out8.png")], capsys)
    assert code == 0, err
    assert sample_bits(tmp_path / "out8.png") == 8
