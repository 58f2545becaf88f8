"""Normal-map EXR and camera JSON: round trips and bad input."""
from __future__ import annotations

import numpy as np
import OpenEXR
import pytest

from statfit.errors import StatfitError
from statfit.io.normalmap import (apply_mask, check_camera_fits, read_camera, read_normal_map, write_camera,
                                  write_normal_map)
from statfit.structures.camera import Camera


@pytest.fixture
def camera():
    return Camera.look_at([0, 0, 50], [0, 0, 0], [0, 1, 0], 30.0, 40, 30)


@pytest.fixture
def normal_map(rng):
    normals = rng.standard_normal((30, 40, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    mask = np.zeros((30, 40), bool)
    mask[5:25, 10:30] = True
    return normals * mask[..., None], mask


def test_round_trip_with_camera_in_header(tmp_path, normal_map, camera):
    normals, mask = normal_map
    write_normal_map(tmp_path / "n.exr", normals, mask, camera)
    loaded = read_normal_map(tmp_path / "n.exr")
    np.testing.assert_array_equal(loaded.mask, mask)
    np.testing.assert_allclose(loaded.normals, normals, atol=1e-6)
    np.testing.assert_allclose(loaded.camera.K.numpy(), camera.K.numpy(), rtol=1e-6)
    np.testing.assert_allclose(loaded.camera.world_to_camera.numpy(), camera.world_to_camera.numpy(), atol=1e-5)


def test_half_floats_without_alpha_use_zero_normals_as_background(tmp_path, normal_map):
    normals, mask = normal_map
    channels = {c: normals[..., i].astype(np.float16) for i, c in enumerate("RGB")}
    with OpenEXR.File({"type": OpenEXR.scanlineimage}, channels) as exr:
        exr.write(str(tmp_path / "h.exr"))
    loaded = read_normal_map(tmp_path / "h.exr")
    np.testing.assert_array_equal(loaded.mask, mask)
    assert loaded.camera is None
    np.testing.assert_allclose(np.linalg.norm(loaded.normals[mask], axis=-1), 1.0, atol=1e-6)


def test_camera_json_round_trip(tmp_path, camera):
    write_camera(tmp_path / "c.json", camera)
    again = read_camera(tmp_path / "c.json")
    np.testing.assert_allclose(again.world_to_camera.numpy(), camera.world_to_camera.numpy())
    assert (again.width, again.height) == (40, 30)


def write_channels(path, channels):
    with OpenEXR.File({"type": OpenEXR.scanlineimage}, channels) as exr:
        exr.write(str(path))
    return path


@pytest.mark.parametrize("case,message", [
    ("missing", "not found"),
    ("garbage", "not an OpenEXR"),
    ("truncated", "damaged"),
    ("no rgb", "no R/G/B"),
    ("all background", "no foreground"),
    ("nan", "NaN"),
])
def test_bad_normal_maps(tmp_path, normal_map, camera, case, message):
    normals, mask = normal_map
    path = tmp_path / "bad.exr"
    if case == "garbage":
        path.write_bytes(b"not an exr at all")
    elif case == "truncated":
        write_normal_map(path, normals, mask, camera)
        path.write_bytes(path.read_bytes()[:200])
    elif case == "no rgb":
        write_channels(path, {"Y": np.ones((4, 4), np.float32)})
    elif case == "all background":
        write_normal_map(path, normals, np.zeros_like(mask))
    elif case == "nan":
        normals = normals.copy()
        normals[10, 15] = np.nan
        write_normal_map(path, normals, mask)
    with pytest.raises(StatfitError, match=message):
        read_normal_map(path)


def test_mask_override_must_match_the_image(tmp_path, normal_map):
    normals, mask = normal_map
    write_normal_map(tmp_path / "n.exr", normals, mask)
    loaded = read_normal_map(tmp_path / "n.exr")
    smaller = np.zeros_like(mask)
    smaller[10:20, 15:25] = True
    assert apply_mask(loaded, smaller, "mask.png").mask.sum() == 100
    with pytest.raises(StatfitError, match="but the normal map is"):
        apply_mask(loaded, np.ones((5, 5), bool), "mask.png")


def test_bad_camera_files(tmp_path):
    (tmp_path / "c.json").write_text("{not json")
    with pytest.raises(StatfitError, match="not valid JSON"):
        read_camera(tmp_path / "c.json")
    (tmp_path / "k.json").write_text('{"width": 4, "height": 4, "K": [[0,0,0],[0,0,0],[0,0,1]], '
                                     '"world_to_camera": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}')
    with pytest.raises(StatfitError, match="singular"):
        read_camera(tmp_path / "k.json")
    with pytest.raises(StatfitError, match="not found"):
        read_camera(tmp_path / "none.json")


def test_camera_of_another_size_is_refused(tmp_path, normal_map):
    normals, mask = normal_map
    write_normal_map(tmp_path / "n.exr", normals, mask)
    loaded = read_normal_map(tmp_path / "n.exr")
    check_camera_fits(Camera.look_at([0, 0, 50], [0, 0, 0], [0, 1, 0], 30.0, 40, 30), loaded, "camera.json")
    with pytest.raises(StatfitError, match="64×64 image but the normal map is 40×30"):
        check_camera_fits(Camera.look_at([0, 0, 50], [0, 0, 0], [0, 1, 0], 30.0, 64, 64), loaded, "camera.json")
