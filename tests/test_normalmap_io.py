"""Normal-map EXR and camera JSON: round trips and bad input."""
from __future__ import annotations

import json

import numpy as np
import OpenEXR
import pytest

from statfit.errors import StatfitError
from statfit.io.mesh import read_mesh
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


def _described(camera: Camera, pose: str, convention: str) -> dict:
    """``camera`` as other tools describe it: its pose as world_to_camera or camera_to_world, with
    OpenCV or OpenGL camera axes (OpenGL's y and z are OpenCV's negated)."""
    world_to_camera = camera.world_to_camera.numpy()
    if convention == "opengl":
        world_to_camera = np.diag([1.0, -1.0, -1.0, 1.0]) @ world_to_camera
    matrix = world_to_camera if pose == "world_to_camera" else np.linalg.inv(world_to_camera)
    return {"width": camera.width, "height": camera.height, "K": camera.K.tolist(), pose: matrix.tolist(),
            "convention": convention}


@pytest.mark.parametrize("pose", ["world_to_camera", "camera_to_world"])
@pytest.mark.parametrize("convention", ["opencv", "opengl"])
def test_a_camera_described_as_other_tools_do_reads_as_the_same_camera(tmp_path, camera, pose, convention):
    """NeRF's and Blender's camera-to-world in OpenGL axes, or statfit's own: the same camera."""
    (tmp_path / "c.json").write_text(json.dumps(_described(camera, pose, convention)))
    again = read_camera(tmp_path / "c.json")
    np.testing.assert_allclose(again.world_to_camera.numpy(), camera.world_to_camera.numpy(), atol=1e-12)
    np.testing.assert_array_equal(again.K.numpy(), camera.K.numpy())


@pytest.mark.parametrize("change, message", [
    (lambda d: d.update(world_to_camera=np.eye(4).tolist()), "both world_to_camera and camera_to_world"),
    (lambda d: d.update(convention="directx"), "'opencv' or 'opengl'"),
    (lambda d: d.update(camera_to_world=np.diag([1.0, 1.0, -1.0, 1.0]).tolist()), "camera_to_world must be rigid"),
    (lambda d: d.pop("camera_to_world"), "lacks world_to_camera or camera_to_world"),
])
def test_bad_camera_descriptions_are_one_line_errors(tmp_path, camera, change, message):
    described = _described(camera, "camera_to_world", "opengl")
    change(described)
    (tmp_path / "c.json").write_text(json.dumps(described))
    with pytest.raises(StatfitError, match=message):
        read_camera(tmp_path / "c.json")


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


def _png(path, normals: np.ndarray, mask: np.ndarray, background: int, alpha: bool):
    """``normals`` (H, W, 3) encoded as other tools save them, (n + 1) / 2 in 8 bits (Pillow), the
    background ``background`` grey, with the mask as alpha or without one."""
    from PIL import Image

    encoded = np.where(mask[..., None], np.round((normals + 1.0) / 2.0 * 255.0), background).astype(np.uint8)
    if alpha:
        encoded = np.concatenate([encoded, (mask * 255).astype(np.uint8)[..., None]], axis=-1)
    Image.fromarray(encoded, "RGBA" if alpha else "RGB").save(path)
    return path


@pytest.mark.parametrize("background, alpha", [(0, False), (255, False), (128, False), (0, True), (200, True)])
def test_a_png_normal_map_reads_as_the_normals_it_was_encoded_from(tmp_path, normal_map, background, alpha):
    """Black, white and mid-grey backgrounds decode far from unit length: the foreground is found
    without an alpha channel too; 8-bit rounding leaves each normal within half a degree."""
    normals, mask = normal_map
    loaded = read_normal_map(_png(tmp_path / "n.png", normals, mask, background, alpha))
    np.testing.assert_array_equal(loaded.mask, mask)
    angles = np.degrees(np.arccos(np.clip((loaded.normals * normals).sum(-1)[mask], -1.0, 1.0)))
    assert angles.max() < 0.5, angles.max()
    assert loaded.camera is None


def test_a_png_normal_map_fits_as_its_exr_does(tmp_path, capsys):
    from test_cli import run

    exr, camera, gt = tmp_path / "n.exr", tmp_path / "cam.json", tmp_path / "gt.ply"
    assert run(["synth", "normals", "--seed", "3", "--size", "96", "--out", str(exr), "--camera-out", str(camera),
                "--gt", str(gt)], capsys)[0] == 0
    exact = read_normal_map(exr)
    png = _png(tmp_path / "n.png", exact.normals, exact.mask, 0, False)
    errors = {}
    for source in (exr, png):
        fit = tmp_path / f"{source.suffix[1:]}_fit.ply"
        code, _, err = run(["render", str(source), "--camera", str(camera), "--out", str(fit), "--iterations", "150",
                            "-q"], capsys)
        assert code == 0, err
        code, out, _ = run(["eval", str(fit), str(gt), "--json"], capsys)
        errors[source.suffix] = json.loads(out)["all"]["mean"]
    assert errors[".png"] < 1.15 * errors[".exr"], errors
    code, _, err = run(["render", str(png), "--out", str(tmp_path / "x.ply")], capsys)
    assert code == 2 and "carries no camera in its header; pass --camera" in err


@pytest.mark.parametrize("image, message", [
    (np.full((8, 8), 128, np.uint8), "a PNG normal map is RGB or RGBA, (n + 1) / 2 per channel; this one is grey"),
    (np.zeros((8, 8, 3), np.uint8), "the mask has no foreground pixel"),
])
def test_a_png_that_is_no_normal_map_is_refused(tmp_path, image, message):
    from PIL import Image

    Image.fromarray(image).save(tmp_path / "n.png")
    with pytest.raises(StatfitError, match=message.replace("(", r"\(").replace(")", r"\)").replace("+", r"\+")):
        read_normal_map(tmp_path / "n.png")


def _sphere(size: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals of a sphere's cap (size, size, 3) and its mask (a quarter of the image background)."""
    u = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    x, y = np.meshgrid(u, u)
    mask = x * x + y * y < 0.9
    return np.stack([x, y, np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, None))], axis=-1) * mask[..., None], mask


@pytest.mark.parametrize("background, alpha", [(0.0, True), (0.0, False), (0.5, False), (1.0, True)])
def test_an_exr_holding_encoded_normals_is_read_as_a_png_is_with_a_warning(tmp_path, background, alpha):
    """(n + 1) / 2 per channel in an EXR: decoded, the background (black, grey, with or without
    alpha) left out, and said; without the decoding every normal would be wrong (their lengths
    0.4–1.4, normalised as they lie)."""
    from statfit.errors import StatfitWarning
    from statfit.io.exr import write_exr

    normals, mask = _sphere()
    encoded = np.where(mask[..., None], (normals + 1.0) / 2.0, background).astype(np.float32)
    channels = {c: encoded[..., i] for i, c in enumerate("RGB")}
    if alpha:
        channels["A"] = mask.astype(np.float32)
    write_exr(tmp_path / "n.exr", channels)
    with pytest.warns(StatfitWarning, match=r"decode as \(n \+ 1\) / 2 to unit normals"):
        loaded = read_normal_map(tmp_path / "n.exr")
    np.testing.assert_array_equal(loaded.mask, mask)
    assert np.abs(loaded.normals - normals)[mask].max() < 1e-5


def test_an_exr_of_unit_normals_facing_one_quadrant_is_read_as_it_is(tmp_path, recwarn):
    """Unit normals with no negative component (all in [0, 1]) are not taken for encoded ones."""
    from statfit.io.exr import write_exr

    normals, mask = _sphere()
    normals = np.abs(normals)
    write_exr(tmp_path / "n.exr", {c: normals[..., i].astype(np.float32) for i, c in enumerate("RGB")})
    loaded = read_normal_map(tmp_path / "n.exr")
    np.testing.assert_array_equal(loaded.mask, mask)
    assert np.abs(loaded.normals - normals)[mask].max() < 1e-6
    assert not recwarn.list


def test_render_fits_an_encoded_exr_as_its_unit_normals_and_says_so(tmp_path, capsys):
    from test_cli import run
    from statfit.io.exr import write_exr

    exr, camera = tmp_path / "n.exr", tmp_path / "cam.json"
    assert run(["synth", "normals", "--seed", "3", "--size", "64", "--out", str(exr), "--camera-out", str(camera)],
               capsys)[0] == 0
    exact = read_normal_map(exr)
    encoded = np.where(exact.mask[..., None], (exact.normals + 1.0) / 2.0, 0.5).astype(np.float32)
    write_exr(tmp_path / "encoded.exr", {c: encoded[..., i] for i, c in enumerate("RGB")})
    fits = []
    for source in (exr, tmp_path / "encoded.exr"):
        fit = tmp_path / f"{source.stem}_fit.ply"
        code, _, err = run(["render", str(source), "--camera", str(camera), "--out", str(fit), "--iterations", "40",
                            "-q"], capsys)
        assert code == 0, err
        fits.append((read_mesh(fit)[0], err))
    assert "decode as (n + 1) / 2" in fits[1][1] and "decode" not in fits[0][1]
    decoded = read_normal_map(tmp_path / "encoded.exr")
    np.testing.assert_array_equal(decoded.mask, exact.mask)
    assert np.abs(decoded.normals - exact.normals)[exact.mask].max() < 1e-6
    # The fits agree within the fit's own floor: normals moved by noise of 1e-7 (1e-6) move this fit
    # 0.11% (0.57%) of the radius on a CPU, and on an H200 the decoding's 1-ulp differences moved it
    # 0.45% (session 43); fitted undecoded, the encoded values move it 78%.
    radius = np.sqrt(((fits[0][0] - fits[0][0].mean(axis=0)) ** 2).sum(axis=1).mean())
    assert np.linalg.norm(fits[1][0] - fits[0][0], axis=1).mean() < 0.02 * radius


def test_a_renders_normal_pass_is_read_as_blender_names_it(tmp_path, normal_map):
    """A multilayer EXR as Blender writes it: the normals from '<layer>.Normal.X/Y/Z', the coverage
    from the layer's 'Combined.A'; the other passes left alone."""
    normals, mask = normal_map
    layer = "ViewLayer."
    channels = {f"{layer}Combined.{c}": np.full(mask.shape, 0.3, np.float32) for c in "RGB"}
    channels[f"{layer}Combined.A"] = mask.astype(np.float32)
    channels[f"{layer}Depth.Z"] = np.full(mask.shape, 7.0, np.float32)
    channels.update({f"{layer}Normal.{axis}": np.ascontiguousarray(normals[..., i]) for i, axis in enumerate("XYZ")})
    loaded = read_normal_map(write_channels(tmp_path / "render.exr", channels))
    np.testing.assert_array_equal(loaded.mask, mask)
    np.testing.assert_allclose(loaded.normals[mask], normals[mask], atol=1e-6)
    channels.update({f"Other.Normal.{axis}": np.ascontiguousarray(normals[..., i]) for i, axis in enumerate("XYZ")})
    with pytest.raises(StatfitError, match="nor a render's Normal.X/Y/Z pass"):   # two: which?
        read_normal_map(write_channels(tmp_path / "two.exr", channels))
