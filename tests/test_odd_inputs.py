"""Odd but parseable models, scans and landmarks (a fuzz of the CLI, 2026-11-28): each either fits
as its well-formed equivalent does, or is refused in one line with exit 2 and nothing written."""
from __future__ import annotations

import warnings

import igl
import numpy as np
import pytest
import torch
import trimesh

from conftest import run_cli
from statfit.core.laplacian import laplacian
from statfit.errors import StatfitError, StatfitWarning
from statfit.geometry.closest import ClosestPointQuery
from statfit.model.cut import decimated
from statfit.model.statmodel import default_model_path, load_model, model_arrays, model_from_arrays
from statfit.registration.pose.scoring import check_plausible

SPARE = 100     # unreferenced vertices added far from the head


@pytest.fixture(scope="module")
def head_scan(tmp_path_factory):
    """The embedded head's synthetic scan and its ground truth (the model's topology)."""
    folder = tmp_path_factory.mktemp("odd")
    scan, gt = folder / "scan.ply", folder / "gt.ply"
    assert run_cli(["synth", "scan", "--seed", "5", "--out", str(scan), "--gt", str(gt)])[0] == 0
    return folder, scan, gt


def _refused(argv: list[str], out) -> str:
    code, err = run_cli(argv + ["--out", str(out), "-q"])
    assert code == 2 and err.count("\n") == 1 and err.startswith("statfit: error:"), (code, err)
    assert not out.exists()
    return err


def _with_spare_vertices(path) -> None:
    """The embedded model plus SPARE vertices no face uses, 1,000 model radii away, without modes."""
    arrays = model_arrays(load_model(default_model_path()))
    spare = np.random.default_rng(0).normal(size=(SPARE, 3)) + 1000.0
    arrays["v_template"] = np.concatenate([arrays["v_template"], spare])
    arrays["shapedirs"] = np.concatenate([arrays["shapedirs"], np.zeros((SPARE, 3, arrays["shapedirs"].shape[2]))])
    np.savez(path, **arrays)


def test_vertices_no_face_uses_change_nothing(head_scan):
    """A model with spare vertices far away fits the scan as the model without them does (the same
    vertices to float32 rounding), with the spare ones left where the template has them: sizes,
    units and the pose are measured on the surface, and the Laplacian gives them no neighbours."""
    folder, scan, _ = head_scan
    spare_model = folder / "spare.npz"
    _with_spare_vertices(spare_model)
    fits = {}
    for name, model in (("plain", default_model_path()), ("spare", spare_model)):
        out = folder / f"{name}.ply"
        code, err = run_cli(["register", str(scan), "--model", str(model), "--out", str(out), "-q"])
        assert code == 0, err
        fits[name] = trimesh.load(out, process=False).vertices
    plain, spare = fits["plain"], fits["spare"]
    size = np.ptp(plain, axis=0).max()
    assert np.abs(spare[:len(plain)] - plain).max() < 1e-5 * size
    assert np.abs(spare[len(plain):] - np.load(spare_model)["v_template"][len(plain):]).max() < 1e-4 * 1000


def test_vertices_no_face_uses_change_no_render_fit(tmp_path):
    """`render` measures the model's image (its units check) and turns the pose about the vertices it
    draws: the spare vertices, 1,000 radii off, once had the fit refused ("139 times the size"). It
    fits as the model without them does, the spare vertices left where the template has them."""
    spare_model = tmp_path / "spare.npz"
    _with_spare_vertices(spare_model)
    normals, camera = tmp_path / "n.exr", tmp_path / "c.json"
    assert run_cli(["synth", "normals", "--seed", "3", "--size", "96", "--out", str(normals),
                    "--camera-out", str(camera)])[0] == 0
    fits = {}
    for name, model in (("plain", default_model_path()), ("spare", spare_model)):
        out = tmp_path / f"{name}.ply"
        code, err = run_cli(["render", str(normals), "--camera", str(camera), "--model", str(model), "--method",
                             "statistical", "--preset", "paper", "--iterations", "30", "--out", str(out), "-q"])
        assert code == 0, err
        fits[name] = trimesh.load(out, process=False).vertices
    plain, spare = fits["plain"], fits["spare"]
    # float32 rounding through the alignment's Adam steps: 4.5e-5 of the size (turning about the
    # centroid of every vertex, spare ones too: 1.2e-3)
    assert np.abs(spare[:len(plain)] - plain).max() < 1e-4 * np.ptp(plain, axis=0).max()
    assert np.abs(spare[len(plain):] - np.load(spare_model)["v_template"][len(plain):]).max() < 1e-4 * 1000


def test_the_uniform_laplacian_has_a_row_for_every_vertex():
    """Vertices past the last one a face uses get empty rows (a Laplacian the size of the mesh)."""
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    matrix = laplacian(np.zeros((6, 3)), faces).toarray()
    expected = np.zeros((6, 6))
    for a, b in ((0, 1), (1, 2), (2, 0), (2, 3), (3, 0)):
        expected[a, b] = expected[b, a] = -1.0
    np.fill_diagonal(expected, -expected.sum(axis=1))
    np.testing.assert_array_equal(matrix, expected)


def test_a_template_without_extent_complex_modes_and_absurd_modes_are_refused():
    model = load_model(default_model_path())
    shapedirs = (model.basis * model.std).reshape(model.num_vertices, 3, -1)
    with pytest.raises(StatfitError, match="all coincide"):
        model_from_arrays(np.ones_like(model.template), model.faces, shapedirs)
    with pytest.raises(StatfitError, match="must be real numbers"):
        model_from_arrays(model.template, model.faces, shapedirs.astype(np.complex64))
    with pytest.raises(StatfitError, match="per standard deviation"):
        model_from_arrays(model.template, model.faces, shapedirs * 1e6)
    model_from_arrays(model.template, model.faces, shapedirs * 1e3)      # large, still a population


def test_the_closest_points_of_a_mesh_with_fewer_vertices_than_neighbours_asked():
    """A tetrahedron (4 vertices) queried with 12 nearest vertices: the closest points are a brute
    force's over its four triangles."""
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    points = np.random.default_rng(1).normal(size=(50, 3))
    found = ClosestPointQuery(faces, 4, k=12)(torch.as_tensor(vertices), torch.as_tensor(points))
    squared, _, _ = igl.point_mesh_squared_distance(points, vertices, faces)
    np.testing.assert_allclose(found.distance.numpy(), np.sqrt(squared), atol=1e-9)


@pytest.mark.parametrize("case", ["collinear", "coincident", "a million times too large"])
def test_landmarks_no_pose_can_come_of_are_refused(head_scan, case, tmp_path):
    _, scan, gt = head_scan
    model = load_model(default_model_path())
    marks = trimesh.load(gt, process=False).vertices[model.landmarks]
    if case == "collinear":
        marks = marks[0] + np.linspace(0.0, 1.0, len(marks))[:, None] * (marks[1] - marks[0])
    elif case == "coincident":
        marks = np.repeat(marks[:1], len(marks), axis=0)
    else:
        marks = marks * 1e6
    path = tmp_path / "marks.txt"
    np.savetxt(path, marks)
    err = _refused(["register", str(scan), "--landmarks", str(path)], tmp_path / "fit.ply")
    assert ("one line" in err) if case != "a million times too large" else ("units" in err)


def test_the_true_landmarks_still_place_the_fit(head_scan, tmp_path):
    _, scan, gt = head_scan
    marks = trimesh.load(gt, process=False).vertices[load_model(default_model_path()).landmarks]
    np.savetxt(tmp_path / "marks.txt", marks)
    code, err = run_cli(["register", str(scan), "--landmarks", str(tmp_path / "marks.txt"),
                         "--out", str(tmp_path / "fit.ply"), "-q"])
    assert code == 0, err


def test_a_fit_that_runs_away_is_refused(head_scan, tmp_path):
    """A step size far too large grows the mesh by orders of magnitude while staying finite."""
    _, scan, _ = head_scan
    err = _refused(["register", str(scan), "--method", "none", "--lr", "10"], tmp_path / "fit.ply")
    assert "diverged" in err


def test_scans_a_similarity_cannot_hold_are_refused(tmp_path):
    """A flat sheet of points the size of a head and points on one line: the similarity ICP shrinks
    the model onto them (×75–80 measured) or there is no surface at all."""
    rng = np.random.default_rng(2)
    sheet = np.c_[rng.uniform(-0.1, 0.1, (500, 2)), np.zeros(500)]
    line = np.outer(np.linspace(-0.1, 0.1, 50), [1.0, 0.5, 0.2])
    for name, points, why in (("sheet", sheet, "ran away"), ("line", line, "one line")):
        path = tmp_path / f"{name}.ply"
        trimesh.PointCloud(points).export(path)
        assert why in _refused(["register", str(path), "--align", "similarity"], tmp_path / f"{name}-fit.ply")


def test_a_cut_that_leaves_a_region_no_triangle_drops_it():
    model = load_model(default_model_path())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        part = decimated(model, 10)
    assert "face" not in part.regions
    assert any(issubclass(w.category, StatfitWarning) and "region(s) face" in str(w.message) for w in caught)


def test_the_refusal_advises_only_what_the_model_allows():
    far = np.full(5, 9.0)
    for has_landmarks, advice in ((True, "--landmarks"), (False, "--align similarity")):
        with pytest.raises(StatfitError, match=advice):
            check_plausible(0.9, 0.1, far, 0.01, has_landmarks)


def test_a_face_cut_of_the_head_is_placed_on_a_scan_of_the_whole_head(head_scan):
    """The embedded head's face region as a model of its own, and a scan of the head's side: the
    pose search's refinement (scale free) scored the mask stretched over the head's side better
    than where it belongs; each refined pose polished at the units' scale puts it back (the
    scan is in the model's frame: the true pose is the identity)."""
    from statfit.io.mesh import load_scan
    from statfit.model.cut import region_part
    from statfit.registration.pose.hypotheses import angle_between
    from statfit.registration.pose.search import estimate_pose

    _, scan, _ = head_scan
    mask = region_part(load_model(default_model_path()), "face")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StatfitWarning)
        pose = estimate_pose(mask, load_scan(str(scan))).transform
    assert angle_between(pose.rotation, np.eye(3)) < 5.0
    assert np.linalg.norm(pose.translation) < 0.05 * mask.frame.scale * 10


def test_a_mesh_is_written_only_as_ply_or_obj(head_scan, tmp_path):
    """A .stl target used to receive PLY bytes (no STL reader opens them): refused before any work."""
    _, scan, _ = head_scan
    for argv in (["register", str(scan), "-q"], ["model", "sample"]):
        code, err = run_cli(argv + ["--out", str(tmp_path / "fit.stl")])
        assert code == 2 and err.count("\n") == 1 and ".ply or .obj" in err, err
        assert not (tmp_path / "fit.stl").exists()


def test_a_texture_model_from_a_folder_without_images_is_refused(tmp_path):
    (tmp_path / "images").mkdir()
    code, err = run_cli(["model", "build-texture", str(tmp_path / "images"), "-o", str(tmp_path / "t.npz"), "-q"])
    assert code == 2 and "no image in the folder" in err and err.count("\n") == 1
    assert not (tmp_path / "t.npz").exists()


def test_evaluation_json_is_json_when_a_row_has_no_vertices(head_scan, tmp_path, capsys):
    """A scan that covers no ground-truth vertex leaves the 'unobserved' row empty: its mean is
    NaN, which JSON cannot hold; it is written as null (a strict parser reads the output)."""
    import json

    from statfit_cli.main import main

    _, scan, gt = head_scan
    far = tmp_path / "far.ply"
    trimesh.PointCloud(trimesh.load(gt, process=False).vertices + 1e3).export(far)
    with pytest.raises(SystemExit) as done:
        main(["eval", str(gt), str(gt), "--scan", str(far), "--json"])
    assert done.value.code in (0, None)
    report = json.loads(capsys.readouterr().out, parse_constant=lambda name: pytest.fail(f"{name} in the JSON"))
    assert report["observed"]["count"] == 0 and report["observed"]["mean"] is None


def test_a_params_file_with_no_persons_coefficients_is_refused(head_scan, tmp_path):
    """A params file whose coefficients are 1e30 standard deviations used to give a mesh 1e28 across."""
    import json

    _, scan, _ = head_scan
    params = tmp_path / "p.json"
    code, err = run_cli(["register", str(scan), "--out", str(tmp_path / "fit.ply"), "--params", str(params), "-q"])
    assert code == 0, err
    assert run_cli(["model", "sample", "--params", str(params), "--out", str(tmp_path / "ok.ply")])[0] == 0
    record = json.loads(params.read_text())
    record["coefficients"] = [1e30] * len(record["coefficients"])
    params.write_text(json.dumps(record))
    code, err = run_cli(["model", "sample", "--params", str(params), "--out", str(tmp_path / "sample.ply")])
    assert code == 2 and err.count("\n") == 1 and "describes no person" in err, err
    assert not (tmp_path / "sample.ply").exists()


def test_a_normal_map_of_a_few_pixels_is_refused_for_what_it_is(tmp_path):
    """One foreground pixel used to be refused with a hint about units (its silhouette is tiny)."""
    from statfit.io.image import write_image

    normals, camera = tmp_path / "n.exr", tmp_path / "c.json"
    assert run_cli(["synth", "normals", "--size", "48", "--out", str(normals), "--camera-out", str(camera)])[0] == 0
    mask = np.zeros((48, 48, 1), np.float32)
    mask[24, 24] = 1.0
    write_image(tmp_path / "mask.png", mask)
    code, err = run_cli(["render", str(normals), "--camera", str(camera), "--mask", str(tmp_path / "mask.png"),
                         "--out", str(tmp_path / "fit.ply"), "-q"])
    assert code == 2 and err.count("\n") == 1 and "1 foreground pixel:" in err, err
    assert not (tmp_path / "fit.ply").exists()


def test_evaluations_of_nothing_are_refused(head_scan, tmp_path):
    """An empty region, a camera that sees none of the ground truth and a fit file whose off_span
    holds NaN used to give a report of NaN rows (or null edges) with exit 0."""
    import json

    from statfit.io.mesh import mesh_bytes, read_mesh

    _, _, gt = head_scan
    arrays = model_arrays(load_model(default_model_path()))
    arrays["region_face"] = np.zeros(0, dtype=np.int64)
    np.savez(tmp_path / "empty_region.npz", **arrays)
    code, err = run_cli(["eval", str(gt), str(gt), "--model", str(tmp_path / "empty_region.npz"), "--region", "face"])
    assert code == 2 and err.count("\n") == 1 and "region 'face' holds no vertex" in err, err

    normals, camera = tmp_path / "n.exr", tmp_path / "c.json"
    assert run_cli(["synth", "normals", "--size", "32", "--out", str(normals), "--camera-out", str(camera)])[0] == 0
    behind = json.loads(camera.read_text())
    behind["world_to_camera"][2][3] = -behind["world_to_camera"][2][3]      # the head now lies behind it
    (tmp_path / "behind.json").write_text(json.dumps(behind))
    code, err = run_cli(["eval", str(gt), str(gt), "--normals", str(normals),
                         "--camera", str(tmp_path / "behind.json")])
    assert code == 2 and err.count("\n") == 1 and "sees no vertex" in err, err

    vertices, faces = read_mesh(gt)
    off_span = np.linspace(0.0, 1.0, len(vertices))
    off_span[:10] = np.nan
    (tmp_path / "nan_field.ply").write_bytes(mesh_bytes(vertices, faces, "ply", {"off_span": off_span}))
    code, err = run_cli(["eval", str(tmp_path / "nan_field.ply"), str(gt)])
    assert code == 2 and err.count("\n") == 1 and "off_span field holds NaN" in err, err


def test_a_camera_of_more_pixels_than_statfit_renders_is_refused():
    """A 20000² splat render grew to the machine's 24 GB and was killed without a word."""
    from statfit.structures.camera import MAX_CAMERA_PIXELS, Camera

    Camera.look_at([0, 0, 3.0], [0, 0, 0], [0, 1, 0], 30.0, 8192, 8192)
    assert 8192 * 8192 == MAX_CAMERA_PIXELS
    with pytest.raises(StatfitError, match="20000×20000 pixels is larger than"):
        Camera.look_at([0, 0, 3.0], [0, 0, 0], [0, 1, 0], 30.0, 20000, 20000)


def test_an_initial_mesh_without_extent_is_refused_for_what_it_is(head_scan, tmp_path):
    """`render --init` with every vertex at one point used to be refused with a hint about units."""
    from statfit.io.mesh import mesh_bytes, read_mesh

    _, _, gt = head_scan
    vertices, faces = read_mesh(gt)
    (tmp_path / "point.ply").write_bytes(mesh_bytes(np.zeros_like(vertices), faces, "ply"))
    normals, camera = tmp_path / "n.exr", tmp_path / "c.json"
    assert run_cli(["synth", "normals", "--size", "32", "--out", str(normals), "--camera-out", str(camera)])[0] == 0
    code, err = run_cli(["render", str(normals), "--camera", str(camera), "--init", str(tmp_path / "point.ply"),
                         "--out", str(tmp_path / "fit.ply"), "-q"])
    assert code == 2 and err.count("\n") == 1 and "all coincide" in err, err
    assert not (tmp_path / "fit.ply").exists()


def test_a_scan_whose_points_tie_at_zero_is_refused_not_a_crash(tmp_path):
    """1,500 of 4,300 points on the plane x = 0 exactly: SciPy's
    KD-tree build recursed without end there while the CLI flushed subnormals, and `statfit
    register` died of a segmentation fault (exit 139, no message). A child process, so a crash
    fails this test instead of killing its worker."""
    import subprocess
    import sys

    points = np.random.default_rng(0).normal(size=(4300, 3)) * 50.0
    points[:1500, 0] = 0.0
    trimesh.PointCloud(points).export(tmp_path / "ties.ply")
    out = tmp_path / "fit.ply"
    done = subprocess.run([sys.executable, "-c", "from statfit_cli.main import main; main()", "register",
                           str(tmp_path / "ties.ply"), "--out", str(out), "-q"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2 and done.stderr.count("\n") == 1, (done.returncode, done.stderr[-2000:])
    assert done.stderr.startswith("statfit: error:") and not out.exists()
