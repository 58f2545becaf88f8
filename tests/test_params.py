"""The model's code of a fit (params file) and where a fit guessed (the fitted PLY's vertex fields),
checked against closed forms on the embedded model."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from statfit.errors import StatfitError
from statfit.geometry.align import Similarity
from statfit.geometry.metrics import off_span_quartiles
from statfit.geometry.support import scan_support, view_support
from statfit.io.mesh import mesh_bytes, read_mesh, read_points, read_vertex_fields
from statfit.io.files import write_atomic
from statfit.model.params import canonical_signs, posed_shape, project, vertex_fields
from statfit.model.params_file import params_bytes, read_params
from statfit.model.statmodel import default_model_path, load_model, model_from_arrays
from statfit.structures.camera import Camera
from statfit_cli.main import main

POSE = Similarity(37.5, Rotation.from_rotvec([0.4, -1.1, 2.0]).as_matrix(), np.array([120.0, -40.0, 15.0]))


@pytest.fixture(scope="module")
def model():
    return load_model(default_model_path())


def off_span_mesh(model, seed: int = 0):
    """Coefficients c, a displacement orthogonal to the span, and the mesh POSE(shape(c) + that)."""
    rng = np.random.default_rng(seed)
    c = rng.standard_normal(model.num_modes)
    noise = 1e-3 * rng.standard_normal(3 * model.num_vertices)
    perpendicular = (noise - model.basis @ (model.basis.T @ noise)).reshape(-1, 3)
    return c, perpendicular, POSE.apply(model.shape(c) + perpendicular)


def run(argv: list[str], capsys) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    out, err = capsys.readouterr()
    return exit_info.value.code, out, err


def test_a_model_shape_projects_to_its_coefficients(model):
    c = np.random.default_rng(1).standard_normal(model.num_modes)
    projection = project(model, POSE.apply(model.shape(c)), POSE)
    np.testing.assert_allclose(projection.coefficients, c, atol=1e-9)
    assert projection.off_span.max() < 1e-9 * np.abs(model.template).max()


def test_the_residual_is_the_part_off_the_span(model):
    c, perpendicular, vertices = off_span_mesh(model)
    projection = project(model, vertices, POSE)
    np.testing.assert_allclose(projection.coefficients, c, atol=1e-9)
    np.testing.assert_allclose(projection.off_span, np.linalg.norm(perpendicular, axis=1), rtol=1e-7, atol=1e-12)
    fields = vertex_fields(projection, np.zeros(model.num_vertices), np.ones(model.num_vertices, bool))
    np.testing.assert_allclose(fields["off_span"], POSE.scale * np.linalg.norm(perpendicular, axis=1), rtol=1e-7)


@pytest.mark.parametrize("suffix", [".json", ".npz"])
def test_write_read_evaluate_gives_the_projection(model, tmp_path, suffix):
    c, perpendicular, vertices = off_span_mesh(model, 2)
    projection = project(model, vertices, POSE, units_factor=100.0)
    path = tmp_path / f"fit{suffix}"
    write_atomic(path, params_bytes(model, projection, path))
    back = read_params(path, model)
    expected = POSE.apply(model.shape(c))     # the closed form: the mesh without its off-span part
    got = posed_shape(model, back)
    assert np.abs(got - expected).max() <= 1e-9 * np.abs(expected).max()
    np.testing.assert_array_equal(back.coefficients, projection.coefficients)
    assert back.transform.scale == POSE.scale and back.units_factor == 100.0
    if suffix == ".json":
        record = json.loads(path.read_text())
        rms = np.sqrt(np.mean(np.sum(perpendicular**2, axis=1)))
        assert record["off_span"]["rms"] == pytest.approx(rms, rel=1e-7)
        assert record["off_span"]["regions"]["face"]["max"] <= record["off_span"]["max"]
        np.testing.assert_allclose(record["similarity"]["rotation_deg"], np.degrees([0.4, -1.1, 2.0]), rtol=1e-9)
        assert "expressions" not in record   # statfit models carry no mode names


def test_coefficients_survive_a_flipped_svd_sign(model, tmp_path):
    c, _, vertices = off_span_mesh(model, 3)
    path = tmp_path / "fit.json"
    write_atomic(path, params_bytes(model, project(model, vertices, POSE), path))
    flip = np.ones(model.num_modes)
    flip[::2] = -1.0
    flipped = dataclasses.replace(model, basis=model.basis * flip)   # another LAPACK's signs
    assert (canonical_signs(flipped) == canonical_signs(model) * flip).all()
    back = read_params(path, flipped)
    np.testing.assert_allclose(back.coefficients, c * flip, atol=1e-9)
    np.testing.assert_allclose(posed_shape(flipped, back), POSE.apply(model.shape(c)), rtol=1e-9, atol=1e-9)


def test_params_of_another_model_or_malformed_are_refused(model, tmp_path):
    path = tmp_path / "fit.json"
    write_atomic(path, params_bytes(model, project(model, POSE.apply(model.template), POSE), path))
    with pytest.raises(StatfitError, match="modes"):
        read_params(path, model.truncated(10))
    small = model_from_arrays(np.eye(3), np.array([[0, 1, 2]]), np.ones((3, 3, 1)))
    with pytest.raises(StatfitError, match="vertices"):
        read_params(path, small)
    moved = dataclasses.replace(model, template=model.template + 1e-3)
    with pytest.raises(StatfitError, match="another model"):
        read_params(path, moved)
    record = json.loads(path.read_text())
    for change, message in ((lambda r: r.update(coefficients=r["coefficients"][:-1]), "coefficients"),
                            (lambda r: r["similarity"].update(rotation=np.diag([1, 1, -1]).tolist()), "rotation"),
                            (lambda r: r["similarity"].update(scale=-1.0), "scale"),
                            (lambda r: r.update(format="other"), "not a statfit params file")):
        broken = json.loads(json.dumps(record))
        change(broken)
        (tmp_path / "bad.json").write_text(json.dumps(broken))
        with pytest.raises(StatfitError, match=message):
            read_params(tmp_path / "bad.json", model)
    (tmp_path / "cut.json").write_text(path.read_text()[:100])
    with pytest.raises(StatfitError, match="not valid JSON"):
        read_params(tmp_path / "cut.json", model)


def test_ply_fields_round_trip_and_plain_meshes_are_unchanged(model, tmp_path):
    vertices = model.template
    fields = {"data_distance": np.linspace(0, 1, model.num_vertices), "observed": np.arange(model.num_vertices) % 3 == 0,
              "off_span": np.full(model.num_vertices, 0.25)}
    write_atomic(tmp_path / "f.ply", mesh_bytes(vertices, model.faces, "ply", fields))
    back, faces = read_mesh(tmp_path / "f.ply")
    np.testing.assert_array_equal(faces, model.faces)
    np.testing.assert_allclose(back, vertices, rtol=1e-6)
    read = read_vertex_fields(tmp_path / "f.ply")
    assert list(read) == list(fields)
    for name, values in fields.items():
        np.testing.assert_allclose(read[name], values.astype(np.float32))
    assert mesh_bytes(vertices, model.faces, "ply") == mesh_bytes(vertices, model.faces, "ply", None)
    assert read_vertex_fields(tmp_path / "nothing.obj") == {}


def test_scan_support_is_the_nearest_point_distance():
    rng = np.random.default_rng(4)
    vertices, points = rng.random((50, 3)), rng.random((400, 3))
    distance, observed = scan_support(vertices, points)
    brute = np.linalg.norm(vertices[:, None] - points[None], axis=2).min(axis=1)
    np.testing.assert_allclose(distance, brute, rtol=1e-12)
    spacing = np.sort(np.linalg.norm(points[:, None] - points[None], axis=2), axis=1)[:, 1]
    np.testing.assert_array_equal(observed, brute <= 3 * np.median(spacing))


def test_view_support_sees_the_front_and_measures_the_back_through_it():
    """Two parallel squares facing the camera, the back one 0.5 behind and smaller: the front is
    observed at distance 0 (its corners lie on covered pixels' points up to a pixel), the back
    unobserved at 0.5 (the nearest seen point is straight in front of it)."""
    front = np.array([[-1.0, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]])
    back = front * [0.5, 0.5, 1] + [0, 0, 0.5]
    vertices = np.concatenate([front, back])
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    camera = Camera.look_at([0, 0, -4.0], [0, 0, 0], [0, -1, 0], 60.0, 128, 128)
    distance, observed = view_support(vertices, faces, [(camera, None)])
    assert observed.tolist() == [True] * 4 + [False] * 4
    assert distance[:4].max() < 0.05
    np.testing.assert_allclose(distance[4:], 0.5, atol=0.02)
    mask = np.zeros((128, 128), bool)   # a mask with no pixel of the mesh: nothing observed
    distance, observed = view_support(vertices, faces, [(camera, mask)])
    assert not observed.any() and np.isinf(distance).all()


def test_off_span_quartiles_split_the_errors():
    off_span = np.array([4.0, 3, 2, 1, 8, 7, 6, 5])
    err = 10 * off_span
    report = off_span_quartiles(err, off_span, scale=1.0)
    assert [report[f"off_span_q{q}"]["mean"] for q in (1, 2, 3, 4)] == [15.0, 35.0, 55.0, 75.0]
    assert report["off_span_edges"][0] == 1.0 and report["off_span_edges"][-1] == 8.0


def test_register_params_sample_and_eval(tmp_path, capsys):
    scan, gt, fit = tmp_path / "scan.ply", tmp_path / "gt.ply", tmp_path / "fit.ply"
    assert run(["synth", "scan", "--seed", "5", "--out", str(scan), "--gt", str(gt)], capsys)[0] == 0
    params, remade = tmp_path / "fit.params.json", tmp_path / "remade.ply"
    code, _, err = run(["register", str(scan), "--out", str(fit), "--params", str(params), "--iterations", "30",
                        "-q"], capsys)
    assert code == 0, err
    assert run(["model", "sample", "--params", str(params), "-o", str(remade)], capsys)[0] == 0
    fitted, sampled = read_mesh(fit)[0], read_mesh(remade)[0]
    fields = read_vertex_fields(fit)
    assert set(fields) == {"data_distance", "observed", "off_span"}
    # the fit and its projection differ by exactly the off-span residual (float32 files)
    np.testing.assert_allclose(np.linalg.norm(fitted - sampled, axis=1), fields["off_span"], atol=2e-6)
    np.testing.assert_allclose(fields["data_distance"], scan_support(fitted, read_points(scan))[0], atol=1e-6)
    code, out, _ = run(["eval", str(fit), str(gt), "--json"], capsys)
    report = json.loads(out)
    assert code == 0 and report["observed"]["count"] == int(fields["observed"].sum())
    assert sum(report[f"off_span_q{q}"]["count"] for q in (1, 2, 3, 4)) == len(fitted)


def test_bad_params_exit_2_and_write_nothing(model, tmp_path, capsys):
    small = tmp_path / "small.npz"
    from statfit.model.statmodel import save_model
    save_model(model.truncated(5), small)
    params = tmp_path / "p.json"
    write_atomic(params, params_bytes(model, project(model, model.template), params))
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    for argv, message in ((["model", "sample", str(small), "--params", str(params)], "50 modes"),
                          (["model", "sample", "--params", str(tmp_path / "junk.npz")], "not an npz"),
                          (["model", "sample", "--params", str(tmp_path / "none.json")], "not found"),
                          (["model", "sample", "--params", str(params), "--seed", "0"], "--seed would not"),
                          (["model", "sample", "--params", str(params), "--sigma", "2", "--seed", "1"],
                           "--sigma and --seed would not")):
        code, _, err = run([*argv, "-o", str(tmp_path / "out.ply")], capsys)
        assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
        assert not (tmp_path / "out.ply").exists()
    code, _, err = run(["register", str(tmp_path / "scan.ply"), "--params", str(tmp_path / "p.txt")], capsys)
    assert code == 2 and ".json or .npz" in err


def test_render_params_fields_and_coloured_preview(tmp_path, capsys):
    exr, camera, gt = tmp_path / "n.exr", tmp_path / "camera.json", tmp_path / "gt.ply"
    assert run(["synth", "normals", "--seed", "3", "--size", "64", "--out", str(exr), "--camera-out", str(camera),
                "--gt", str(gt)], capsys)[0] == 0
    fit, params, preview = tmp_path / "fit.ply", tmp_path / "fit.params.npz", tmp_path / "fit.png"
    code, _, err = run(["render", str(exr), "--camera", str(camera), "--out", str(fit), "--params", str(params),
                        "--preview", str(preview), "--preview-colour", "off_span", "--iterations", "20", "-q"], capsys)
    assert code == 0, err
    fields = read_vertex_fields(fit)
    assert 0 < fields["observed"].sum() < len(fields["observed"])
    seen = fields["observed"] > 0.5   # the seen side lies on its own covered pixels' points, the rest behind
    assert np.median(fields["data_distance"][seen]) < 0.25 * np.median(fields["data_distance"][~seen])
    remade = tmp_path / "remade.ply"
    assert run(["model", "sample", "--params", str(params), "-o", str(remade)], capsys)[0] == 0
    np.testing.assert_allclose(np.linalg.norm(read_mesh(fit)[0] - read_mesh(remade)[0], axis=1), fields["off_span"],
                               atol=2e-6)
    assert preview.stat().st_size > 0
    code, _, err = run(["render", str(exr), "--camera", str(camera), "--preview-colour", "depth"], capsys)
    assert code == 2 and "--preview-colour" in err


def test_batch_writes_params_beside_each_mesh(tmp_path, capsys):
    scans = tmp_path / "scans"
    scans.mkdir()
    for seed in (1, 2):
        assert run(["synth", "scan", "--seed", str(seed), "--out", str(scans / f"s{seed}.ply")], capsys)[0] == 0
    out = tmp_path / "fits"
    code, _, err = run(["batch", "register", str(scans / "*.ply"), "--out-dir", str(out), "--params", "--iterations",
                        "20", "--workers", "1", "-q"], capsys)
    assert code == 0, err
    model = load_model(default_model_path())
    for seed in (1, 2):
        projection = read_params(out / f"s{seed}.params.json", model)
        fitted = read_mesh(out / f"s{seed}.ply")[0]
        off_span = read_vertex_fields(out / f"s{seed}.ply")["off_span"]
        np.testing.assert_allclose(np.linalg.norm(fitted - posed_shape(model, projection), axis=1), off_span,
                                   atol=2e-6)


def test_splat_params_and_fields(tmp_path, capsys):
    views, fit, params = tmp_path / "views", tmp_path / "fit.ply", tmp_path / "fit.params.json"
    assert run(["synth", "views", "--views", "3", "--size", "32", "--out", str(views)], capsys)[0] == 0
    code, _, err = run(["splat", str(views), "--iterations", "4", "-q", "--out", str(fit), "--params", str(params)],
                       capsys)
    assert code == 0, err
    record = json.loads(params.read_text())
    assert record["similarity"]["scale"] == 1.0 and record["similarity"]["translation"] == [0.0, 0.0, 0.0]
    fields = read_vertex_fields(fit)
    assert 0 < fields["observed"].sum() and np.isfinite(fields["data_distance"]).all()
