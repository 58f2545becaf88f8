"""`statfit synth normals` → `statfit render` → `statfit eval --normals` on the embedded model, and
bad input to them (one line, exit 2, nothing written)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
import trimesh
from PIL import Image

from statfit.io.normalmap import read_camera, read_normal_map, write_normal_map
from test_cli import corrupt, run

FAST = ["--iterations", "40", "-q"]
SIZE = "96"


@pytest.fixture(scope="module")
def normal_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("normals")
    with pytest.raises(SystemExit) as exit_info:
        from statfit_cli.main import main
        main(["synth", "normals", "--seed", "3", "--size", SIZE, "--out", str(folder / "n.exr"),
              "--camera-out", str(folder / "camera.json"), "--gt", str(folder / "gt.ply")])
    assert exit_info.value.code == 0
    return folder / "n.exr", folder / "camera.json", folder / "gt.ply"


def test_synth_render_eval(normal_files, tmp_path, capsys):
    exr, camera, gt = normal_files
    fit, log, preview = tmp_path / "fit.ply", tmp_path / "fit.jsonl", tmp_path / "fit.png"
    code, out, err = run(["render", str(exr), "--camera", str(camera), "--method", "statistical", "--out", str(fit),
                          "--log", str(log), "--preview", str(preview), "--json", *FAST], capsys)
    assert code == 0, err
    summary = json.loads(out)
    assert summary["iterations"] == 40 and summary["stage_seconds"]["alignment"] > 0
    assert summary["threads"] == 1   # a small model and map run on one thread, whatever the machine
    lines = [json.loads(line) for line in log.read_text().splitlines()]
    assert [lines[0]["type"], lines[-1]["type"]] == ["header", "summary"]
    assert {"normal", "silhouette", "total"} <= set(lines[1])
    assert lines[0]["camera"] == read_camera(camera).to_dict()
    with Image.open(preview) as image:
        assert image.format == "PNG" and image.size[0] > 3 * image.size[1]
    mesh, truth = trimesh.load(fit, process=False), trimesh.load(gt, process=False)
    np.testing.assert_array_equal(mesh.faces, truth.faces)
    code, out, _ = run(["eval", str(fit), str(gt), "--normals", str(exr), "--camera", str(camera), "--json"], capsys)
    report = json.loads(out)
    assert code == 0 and 0 < report["observed"]["count"] < len(mesh.vertices)
    assert report["observed"]["count"] + report["unobserved"]["count"] == len(mesh.vertices)


def test_the_same_map_gives_the_same_mesh_twice(normal_files, tmp_path, capsys):
    """The default fit, twice in one process, on the suite's device: the same bytes (CUDA's
    reductions are made deterministic, statfit.core.device.same_seed_same_bytes)."""
    exr, camera, _ = normal_files
    for name in ("a.ply", "b.ply"):
        code, _, err = run(["render", str(exr), "--camera", str(camera), "--out", str(tmp_path / name), *FAST], capsys)
        assert code == 0, err
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()


def test_camera_from_the_exr_header_and_the_json_agree(normal_files, tmp_path, capsys):
    exr, camera, _ = normal_files
    in_header, in_json = read_normal_map(exr).camera, read_camera(camera)
    np.testing.assert_allclose(in_header.K.numpy(), in_json.K.numpy(), rtol=1e-6)
    np.testing.assert_allclose(in_header.world_to_camera.numpy(), in_json.world_to_camera.numpy(), atol=1e-6)
    outputs = []
    for name, extra in (("a.ply", ["--camera", str(camera)]), ("b.ply", [])):
        assert run(["render", str(exr), *extra, "--align", "none", "--out", str(tmp_path / name), *FAST], capsys)[0] == 0
        outputs.append(trimesh.load(tmp_path / name, process=False).vertices)
    # The header holds float32 (the standard worldToCamera is an M44f): the fits agree to 0.2% of the size.
    np.testing.assert_allclose(outputs[0], outputs[1], atol=2e-3 * np.ptp(outputs[0], axis=0).max())


def _camera_space_copy(exr: Path, path: Path, convention: str) -> Path:
    """The same map with its normals rotated into camera space (OpenCV or OpenGL axes)."""
    normal_map = read_normal_map(exr)
    normals = normal_map.normals @ normal_map.camera.rotation.numpy().T.astype(np.float32)
    if convention == "opengl":
        normals = normals * np.array([1, -1, -1], dtype=np.float32)
    write_normal_map(path, normals * normal_map.mask[..., None], normal_map.mask, normal_map.camera)
    return path


@pytest.mark.parametrize("convention", ["opencv", "opengl"])
def test_camera_space_normals_give_the_world_space_result(normal_files, tmp_path, capsys, convention):
    exr, _, _ = normal_files
    local = _camera_space_copy(exr, tmp_path / "local.exr", convention)
    assert run(["render", str(exr), "--align", "none", "--out", str(tmp_path / "world.ply"), *FAST], capsys)[0] == 0
    assert run(["render", str(local), "--normal-space", "camera", "--normal-convention", convention, "--align", "none",
                "--out", str(tmp_path / "local.ply"), *FAST], capsys)[0] == 0
    world = trimesh.load(tmp_path / "world.ply", process=False).vertices
    local = trimesh.load(tmp_path / "local.ply", process=False).vertices
    np.testing.assert_allclose(local, world, atol=1e-3 * np.ptp(world, axis=0).max())


@pytest.mark.parametrize("stored, read, advice", [
    ("world", ["--normal-space", "camera"], "world-space normals (--normal-space world)"),
    ("opencv", [], "camera-space (OpenCV) normals (--normal-space camera --normal-convention opencv)"),
    ("opengl", ["--normal-space", "camera"],
     "camera-space (OpenGL) normals (--normal-space camera --normal-convention opengl)"),
])
def test_a_map_read_in_another_frame_than_its_own_is_refused_naming_its_own(normal_files, tmp_path, capsys, stored,
                                                                          read, advice):
    """Normals of a visible surface face the camera: read in the wrong frame they face away (every
    test map's in its own frame: ≥ 93% of the foreground faces the camera; in another ≤ 3%)."""
    from statfit.render.framing import camera_space_normals, facing_share

    exr, camera, _ = normal_files
    source = exr if stored == "world" else _camera_space_copy(exr, tmp_path / "local.exr", stored)
    normal_map, pinhole = read_normal_map(source), read_camera(camera)
    own = ("world", "opencv") if stored == "world" else ("camera", stored)
    assert facing_share(camera_space_normals(normal_map, pinhole, *own), normal_map.mask, pinhole) >= 0.9
    code, _, err = run(["render", str(source), *read, "--out", str(tmp_path / "f.ply"), *FAST], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "face away from the camera" in err and advice in err, err
    assert not (tmp_path / "f.ply").exists()


def test_a_blender_render_and_camera_fit_as_statfits_own_files(normal_files, tmp_path, capsys):
    """What a Blender user brings: a multilayer EXR whose normal pass is '<layer>.Normal.X/Y/Z'
    (world space, the coverage in 'Combined.A', no camera in it) and the camera as its matrix_world
    (camera-to-world, OpenGL axes): the fit of statfit's own map and camera."""
    from statfit.io.exr import write_exr

    exr, camera, _ = normal_files
    normal_map, own = read_normal_map(exr), read_camera(camera)
    channels = {f"ViewLayer.Normal.{axis}": normal_map.normals[..., i] for i, axis in enumerate("XYZ")}
    channels |= {"ViewLayer.Combined.A": normal_map.mask.astype(np.float32),
                 "ViewLayer.Depth.Z": np.where(normal_map.mask, 5.0, 1e10).astype(np.float32)}
    write_exr(tmp_path / "render.exr", channels)
    matrix_world = np.linalg.inv(np.diag([1.0, -1.0, -1.0, 1.0]) @ own.world_to_camera.numpy())
    (tmp_path / "blender.json").write_text(json.dumps({"width": own.width, "height": own.height, "K": own.K.tolist(),
                                                       "camera_to_world": matrix_world.tolist(),
                                                       "convention": "opengl"}))
    fits = []
    for source, pinhole in ((exr, camera), (tmp_path / "render.exr", tmp_path / "blender.json")):
        out = tmp_path / f"{Path(pinhole).stem}.ply"
        code, _, err = run(["render", str(source), "--camera", str(pinhole), "--align", "none", "--out", str(out),
                            *FAST], capsys)
        assert code == 0, err
        fits.append(trimesh.load(out, process=False).vertices)
    np.testing.assert_allclose(fits[1], fits[0], atol=1e-6 * np.ptp(fits[0], axis=0).max())


def test_mask_png_restricts_the_fit(normal_files, tmp_path, capsys):
    exr, _, _ = normal_files
    mask = read_normal_map(exr).mask.copy()
    mask[: mask.shape[0] // 2] = False                            # keep the lower half only
    Image.fromarray((mask * 255).astype(np.uint8)).save(tmp_path / "mask.png")
    code, _, err = run(["render", str(exr), "--mask", str(tmp_path / "mask.png"), "--out", str(tmp_path / "f.ply"),
                        *FAST], capsys)
    assert code == 0, err


def test_init_mesh_starts_the_fit(normal_files, tmp_path, capsys):
    exr, _, gt = normal_files
    code, out, _ = run(["render", str(exr), "--init", str(gt), "--align", "none", "--out", str(tmp_path / "f.ply"),
                        "--iterations", "1", "--json", "-q"], capsys)
    assert code == 0
    fitted = trimesh.load(tmp_path / "f.ply", process=False).vertices
    truth = trimesh.load(gt, process=False).vertices
    # One small step from the ground truth stays next to it.
    assert np.abs(fitted - truth).max() < 0.02 * np.ptp(truth, axis=0).max()


def _rgb_less(exr: Path, path: Path) -> Path:
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"Y": np.ones((8, 8), np.float32)}) as image:
        image.write(str(path))
    return path


def _edited(exr: Path, path: Path, edit) -> Path:
    normal_map = read_normal_map(exr)
    normals, mask = normal_map.normals.copy(), normal_map.mask.copy()
    edit(normals, mask)
    write_normal_map(path, normals, mask, normal_map.camera)
    return path


def _camera(camera: Path, path: Path, **changes) -> Path:
    data = json.loads(camera.read_text()) | changes
    path.write_text(json.dumps(data))
    return path


def _black_png(path: Path, exr: Path) -> Path:
    Image.fromarray(np.zeros(read_normal_map(exr).mask.shape, np.uint8)).save(path)
    return path


def _headerless(exr: Path, path: Path) -> Path:
    normal_map = read_normal_map(exr)
    write_normal_map(path, normal_map.normals, normal_map.mask)
    return path


BAD_RENDER_INPUTS = {
    "missing normal map": lambda t, e, c: ["render", str(t / "nope.exr")],
    "corrupt normal map": lambda t, e, c: ["render", str(corrupt(t / "bad.exr"))],
    "truncated normal map": lambda t, e, c: ["render", str((t / "cut.exr").write_bytes(e.read_bytes()[:2000])
                                                           and t / "cut.exr")],
    "no RGB channels": lambda t, e, c: ["render", str(_rgb_less(e, t / "y.exr"))],
    "all background": lambda t, e, c: ["render", str(e), "--mask", str(_black_png(t / "black.png", e))],
    "NaN normals": lambda t, e, c: ["render", str(_edited(e, t / "nan.exr",
                                                          lambda n, m: n.__setitem__(np.nonzero(m), np.nan)))],
    "camera of another size": lambda t, e, c: ["render", str(e), "--camera", str(_camera(c, t / "c.json", width=64))],
    "singular K": lambda t, e, c: ["render", str(e), "--camera",
                                   str(_camera(c, t / "c.json", K=[[0, 0, 48], [0, 0, 48], [0, 0, 1]]))],
    "camera not JSON": lambda t, e, c: ["render", str(e), "--camera", str(corrupt(t / "c.json"))],
    "no camera": lambda t, e, c: ["render", str(_headerless(e, t / "plain.exr"))],
    "unknown normal space": lambda t, e, c: ["render", str(e), "--normal-space", "tangent"],
    "unwritable preview": lambda t, e, c: ["render", str(e), "--preview", "/proc/forbidden/fit.png"],
    "init of another topology": lambda t, e, c: ["render", str(e), "--init", str(_tetrahedron(t / "tet.ply"))],
    "model in other units": lambda t, e, c: ["render", str(e), "--camera",
                                             str(_camera(c, t / "c.json", world_to_camera=_far(c)))],
    "eval --camera without --normals": lambda t, e, c: ["eval", str(e), str(e), "--camera", str(c)],
    "synth normals of zero size": lambda t, e, c: ["synth", "normals", "--size", "0", "--out", str(t / "fit.exr")],
    "empty normal map": lambda t, e, c: ["render", str(_empty(t / "empty.exr"))],
    "missing mask": lambda t, e, c: ["render", str(e), "--mask", str(t / "nope.png")],
    "empty mask": lambda t, e, c: ["render", str(e), "--mask", str(_empty(t / "empty.png"))],
    "corrupt mask": lambda t, e, c: ["render", str(e), "--mask", str(corrupt(t / "bad.png"))],
    "missing camera": lambda t, e, c: ["render", str(e), "--camera", str(t / "nope.json")],
    "empty camera": lambda t, e, c: ["render", str(e), "--camera", str(_empty(t / "empty.json"))],
    "missing init": lambda t, e, c: ["render", str(e), "--init", str(t / "nope.ply")],
    "empty init": lambda t, e, c: ["render", str(e), "--init", str(_empty(t / "empty.ply"))],
    "eval with a missing normal map": lambda t, e, c: ["eval", str(c.parent / "gt.ply"), str(c.parent / "gt.ply"),
                                                       "--normals", str(t / "nope.exr")],
    "synth normals with a missing delta file": lambda t, e, c: ["synth", "normals", "--out", str(t / "fit.exr"),
                                                                "--delta", str(t / "none.npz"), "--delta-name", "jawOpen"],
}


def _empty(path: Path) -> Path:
    path.write_bytes(b"")
    return path


def _tetrahedron(path: Path) -> Path:
    trimesh.creation.icosahedron().export(path)
    return path


def _far(camera: Path) -> list:
    """The camera moved 1000× farther away: the model's image shrinks to a dot."""
    data = json.loads(camera.read_text())
    pose = np.array(data["world_to_camera"])
    pose[:3, 3] *= 1000.0
    return pose.tolist()


@pytest.mark.parametrize("case", sorted(BAD_RENDER_INPUTS))
def test_bad_render_input_gives_one_line_and_exit_2(case, normal_files, tmp_path, capsys):
    exr, camera, _ = normal_files
    before = exr.read_bytes(), camera.read_bytes()
    argv = BAD_RENDER_INPUTS[case](tmp_path, exr, camera)
    if argv[0] == "render":
        argv += ["--out", str(tmp_path / "fit.ply"), "--log", str(tmp_path / "fit.jsonl"), *FAST]
    code, out, err = run(argv, capsys)
    assert code == 2, err
    assert err.startswith("statfit: error: ") and err.count("\n") == 1, err
    assert (exr.read_bytes(), camera.read_bytes()) == before
    assert not [p for p in tmp_path.rglob("*") if p.name.startswith("fit")]


def test_render_help_teaches(capsys):
    code, out, _ = run(["render", "--help"], capsys)
    assert code == 0 and "--normal-space" in out and "--preview" in out and "--align" in out


def test_the_render_default_runs_its_three_stages_from_the_command_line(normal_files, tmp_path, capsys):
    """render's default: two hybrid stages, then the Laplacian filter, its iterations split in
    proportion (150 : 300 : 600) when --iterations sets the total (the log's header lists them)."""
    exr, camera, _ = normal_files
    log = tmp_path / "fit.jsonl"
    code, out, err = run(["render", str(exr), "--camera", str(camera), "--out", str(tmp_path / "fit.ply"),
                          "--log", str(log), "--json", *FAST], capsys)
    assert code == 0, err
    assert json.loads(out)["iterations"] == 40
    stages = json.loads(log.read_text().splitlines()[0])["stages"]
    assert [s["method"] for s in stages] == ["hybrid", "hybrid", "laplacian"]
    assert [s["beta"] for s in stages[:2]] == [30.0, 10.0] and sum(s["iterations"] for s in stages) == 40
    code, _, err = run(["render", str(exr), "--camera", str(camera), "--method", "span-first", "--out",
                        str(tmp_path / "r.ply")], capsys)
    assert code == 2 and "span-first" in err and not (tmp_path / "r.ply").exists()   # withdrawn in session 9
