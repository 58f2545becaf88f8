"""``statfit model import/build/sample/info``, ``--model`` with original files, ``register --region``
and ``--landmarks``, and their bad inputs (one line, exit 2, nothing written, inputs unchanged)."""
from __future__ import annotations

import json
import pickle
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from model_files import random_smpl_arrays, write_flame_masks, write_flame_pickle
from statfit.model.statmodel import default_model_path, load_model, model_arrays
from test_cli import FAST, run


@pytest.fixture(autouse=True)
def _threads():
    """One torch thread (overrides conftest's two): with the second core busy, two threads made these
    fits 4× slower (77 s vs 18 s for the three model-tooling test files, measured)."""
    torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def _cache(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("STATFIT_CACHE_DIR", str(tmp_path_factory.mktemp("cache")))


@pytest.fixture(scope="module")
def flame_pickle(tmp_path_factory, embedded_model):
    """The embedded model as a FLAME 2020-style chumpy pickle (same template, faces and directions)."""
    arrays = random_smpl_arrays(np.random.default_rng(0), n=embedded_model.num_vertices, k=4)
    arrays.update(v_template=embedded_model.template, f=embedded_model.faces.astype(np.uint32),
                  shapedirs=model_arrays(embedded_model)["shapedirs"])
    return write_flame_pickle(tmp_path_factory.mktemp("flame") / "generic_model.pkl", arrays)


def mean_error(fit: Path, gt: Path, vertices: np.ndarray | None = None) -> float:
    error = np.linalg.norm(trimesh.load(fit, process=False).vertices - trimesh.load(gt, process=False).vertices, axis=1)
    return float(error.mean() if vertices is None else error[vertices].mean())


def test_import_info_and_fit_with_the_original_file(flame_pickle, scan_files, tmp_path, capsys, embedded_model):
    masks = write_flame_masks(tmp_path / "FLAME_masks.pkl", {"face": embedded_model.regions["face"]})
    np.savetxt(tmp_path / "landmarks.txt", embedded_model.landmarks, fmt="%d")
    code, out, _ = run(["model", "import", str(flame_pickle), "--masks", str(masks), "--landmarks",
                        str(tmp_path / "landmarks.txt"), "-o", str(tmp_path / "flame.npz")], capsys)
    assert code == 0 and f"{embedded_model.num_vertices} vertices" in out
    imported = load_model(tmp_path / "flame.npz")
    np.testing.assert_allclose(imported.std, embedded_model.std, rtol=1e-8)
    np.testing.assert_array_equal(imported.regions["face"], embedded_model.regions["face"])
    np.testing.assert_array_equal(imported.landmarks, embedded_model.landmarks)
    info = [json.loads(run(["model", "info", str(p), "--json"], capsys)[1]) for p in (tmp_path / "flame.npz", flame_pickle)]
    assert info[0]["modes"] == info[1]["modes"] == embedded_model.num_modes
    assert info[0]["units_guess"] == "metres (head-sized)"
    scan, gt = scan_files
    for model in (default_model_path(), flame_pickle):
        assert run(["register", str(scan), "--model", str(model), "-o", str(tmp_path / f"{model.stem}.ply"), *FAST],
                   capsys)[0] == 0
    # The same distribution, read from the pickle, fits as well as the embedded npz does.
    reference = mean_error(tmp_path / "default_head.ply", gt)
    assert mean_error(tmp_path / "generic_model.ply", gt) == pytest.approx(reference, rel=0.05)


def test_build_then_sample(tmp_path, capsys, embedded_model):
    for seed in range(8):
        assert run(["model", "sample", "--seed", str(seed), "--sigma", "1", "-o", str(tmp_path / f"s{seed}.ply")],
                   capsys)[0] == 0
    code, out, _ = run(["model", "build", *map(str, sorted(tmp_path.glob("s*.ply"))), "-o", str(tmp_path / "mine.npz"),
                        "--k", "3", "--json"], capsys)
    report = json.loads(out)
    assert code == 0 and report["modes"] == 3 and report["meshes"] == 8
    assert 0 < report["variance_explained"]["1"] < report["variance_explained"]["3"] < 1
    built = load_model(tmp_path / "mine.npz")
    # Every built direction lies in the embedded model's span (the samples do).
    residual = built.basis - embedded_model.basis @ (embedded_model.basis.T @ built.basis)
    assert np.abs(residual).max() < 1e-6
    assert run(["model", "sample", str(tmp_path / "mine.npz"), "--sigma", "0", "-o", str(tmp_path / "t.obj")],
               capsys)[0] == 0
    np.testing.assert_allclose(trimesh.load(tmp_path / "t.obj", process=False, maintain_order=True).vertices,
                               built.template, atol=1e-6)


def test_region_fit_ignores_scan_points_of_other_parts(scan_files, tmp_path, capsys, embedded_model):
    """A 3 cm 'hat' over every scan point off the face: the full fit bends the face towards it, the
    face-region fit does not, and the rest of its head follows the prior (stays near the truth, far
    from the hat)."""
    scan, gt = scan_files
    truth = trimesh.load(gt, process=False)
    points = trimesh.load(scan).vertices
    face = np.zeros(embedded_model.num_vertices, dtype=bool)
    face[embedded_model.regions["face"]] = True
    _, nearest = cKDTree(truth.vertices).query(points)
    off_face = ~face[nearest]
    points[off_face] += 0.03 * truth.vertex_normals[nearest[off_face]]
    trimesh.PointCloud(points).export(tmp_path / "hat.ply")
    for name, extra in (("full", []), ("face", ["--region", "face"])):
        assert run(["register", str(tmp_path / "hat.ply"), "-o", str(tmp_path / f"{name}.ply"), "--align", "none",
                    *extra, *FAST], capsys)[0] == 0
    full_face, region_face = (mean_error(tmp_path / f"{n}.ply", gt, face) for n in ("full", "face"))
    assert region_face < 0.25 * full_face
    assert mean_error(tmp_path / "face.ply", gt, ~face) < 0.2 * 0.03
    code, out, _ = run(["eval", str(tmp_path / "face.ply"), str(gt), "--model", str(default_model_path()),
                        "--region", "face", "--json"], capsys)
    assert code == 0 and json.loads(out)["all"]["count"] == face.sum()
    assert json.loads(out)["all"]["mean"] == pytest.approx(region_face)


def test_landmarks_align_a_rotated_scan_in_millimetres(scan_files, tmp_path, capsys, embedded_model):
    scan, gt = scan_files
    rotation = Rotation.from_rotvec(np.radians(120) * np.array([1, 1, 0]) / np.sqrt(2)).as_matrix()

    def moved(p):
        return 1000 * p @ rotation.T + [50.0, -20.0, 300.0]

    truth = trimesh.load(gt, process=False)
    trimesh.PointCloud(moved(trimesh.load(scan).vertices)).export(tmp_path / "scan_mm.ply")
    trimesh.Trimesh(moved(truth.vertices), truth.faces, process=False).export(tmp_path / "gt_mm.ply")
    landmarks = moved(truth.vertices[embedded_model.landmarks])
    landmarks[1] = np.nan  # a missing landmark
    np.savetxt(tmp_path / "landmarks.txt", landmarks)
    radius = 1000 * np.sqrt(((truth.vertices - truth.vertices.mean(0)) ** 2).sum(1).mean())
    for name, extra in (("lm", ["--landmarks", str(tmp_path / "landmarks.txt")]), ("icp", ["--align", "similarity"])):
        assert run(["register", str(tmp_path / "scan_mm.ply"), "-o", str(tmp_path / f"{name}.ply"), *extra, *FAST],
                   capsys)[0] == 0
    assert mean_error(tmp_path / "lm.ply", tmp_path / "gt_mm.ply") < 0.05 * radius
    assert mean_error(tmp_path / "icp.ply", tmp_path / "gt_mm.ply") > 0.5 * radius  # ICP alone cannot turn 120°


def _malicious(path: Path) -> Path:
    class Exploit:
        def __reduce__(self):
            import os
            return os.system, (f"touch {path.parent / 'pwned'}",)

    path.write_bytes(pickle.dumps({"v_template": Exploit()}, protocol=2))
    return path


def _pickle(path: Path, obj) -> Path:
    path.write_bytes(pickle.dumps(obj, protocol=2))
    return path


def _h5_without_groups(path: Path) -> Path:
    with h5py.File(path, "w") as handle:
        handle["color/model/mean"] = np.zeros(9, dtype=np.float32)
    return path


def _ply(path: Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    trimesh.Trimesh(vertices, faces, process=False).export(path)
    return path


def _no_landmarks_model(path: Path) -> Path:
    arrays = model_arrays(load_model(default_model_path()))
    np.savez(path, **{k: v for k, v in arrays.items() if k != "landmarks"})
    return path


def _light_layout_model(path: Path, face_count=40, landmarks=None) -> Path:
    """The embedded model in the light ICT-FaceKit npz layout (../shared/data/ict-face/README.md): its
    landmarks as ``landmarks68``, a face as ``face_vertex_count``, no contract keys for either."""
    arrays = model_arrays(load_model(default_model_path()))
    own = arrays.pop("landmarks")
    arrays = {k: v for k, v in arrays.items() if not k.startswith("region_")}
    np.savez(path, **arrays, landmarks68=own.astype(np.int32) if landmarks is None else landmarks,
             face_vertex_count=np.asarray(face_count))
    return path


def test_the_light_ict_layouts_landmarks_and_face_are_read_by_every_command_and_kept_by_import(
        scan_files, tmp_path, capsys):
    """The light ICT-FaceKit npz (../shared/data/ict-face) as ``--model``: its ``landmarks68`` are the
    model's landmarks and ``face_vertex_count`` its ``face_geometry`` region, for every command as for
    ``model import``; the contract's own reader leaves them out."""
    light = _light_layout_model(tmp_path / "light.npz")
    landmarks = load_model(default_model_path()).landmarks
    plain = load_model(light)
    assert plain.landmarks is None and plain.regions == {}
    code, out, _ = run(["model", "info", str(light), "--json"], capsys)
    report = json.loads(out)
    assert code == 0 and report["unread_keys"] == [] and report["landmarks"] == landmarks.size
    assert report["regions"] == {"face_geometry": 40}
    # register takes scan landmarks with it: before, "the model has no landmarks", exit 2
    scan, gt = scan_files
    np.savetxt(tmp_path / "scan_landmarks.txt", trimesh.load(gt, process=False).vertices[landmarks])
    code, _, err = run(["register", str(scan), "--model", str(light), "--landmarks",
                        str(tmp_path / "scan_landmarks.txt"), "-o", str(tmp_path / "fit.ply"), *FAST], capsys)
    assert code == 0, err
    code, out, err = run(["model", "import", str(light), "-o", str(tmp_path / "imported.npz")], capsys)
    assert code == 0, err
    assert f"{landmarks.size} landmarks, regions face_geometry" in out
    imported = load_model(tmp_path / "imported.npz")
    np.testing.assert_array_equal(imported.landmarks, landmarks)
    np.testing.assert_array_equal(imported.regions["face_geometry"], np.arange(40))
    assert "face" not in imported.regions  # the hair rules' face stays the landmarks' neighbourhood
    code, out, _ = run(["model", "info", str(tmp_path / "imported.npz"), "--json"], capsys)
    assert json.loads(out)["unread_keys"] == [] and json.loads(out)["landmarks"] == landmarks.size
    # the user's own landmark file wins over the file's
    (tmp_path / "mine.txt").write_text("0 1 2 3")
    assert run(["model", "import", str(light), "--landmarks", str(tmp_path / "mine.txt"), "-o",
                str(tmp_path / "mine.npz")], capsys)[0] == 0
    np.testing.assert_array_equal(load_model(tmp_path / "mine.npz").landmarks, [0, 1, 2, 3])


def test_a_bad_light_layout_is_refused_by_a_fitting_command_in_one_line(scan_files, tmp_path, capsys):
    scan, _ = scan_files
    code, _, err = run(["register", str(scan), "--model", str(_light_layout_model(tmp_path / "m.npz", 10**6)),
                        "-o", str(tmp_path / "fit.ply"), *FAST], capsys)
    assert code == 2 and "face_vertex_count must be one whole number" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "fit.ply").exists()


def _tetra(t: Path, name: str, faces: list) -> Path:
    return _ply(t / name, np.eye(4, 3) + np.arange(4)[:, None] * 0.1, np.array(faces))


BAD_INPUTS = {
    "pickle of a list": lambda t, s: ["model", "import", str(_pickle(t / "m.pkl", [1, 2])), "-o", str(t / "out.npz")],
    "pickle without keys": lambda t, s: ["model", "import", str(_pickle(t / "m.pkl", {"a": 1})), "-o", str(t / "out.npz")],
    "shapedirs of another vertex count": lambda t, s: [
        "model", "import", str(_pickle(t / "m.pkl", {"v_template": np.zeros((4, 3)), "f": np.array([[0, 1, 2]]),
                                                     "shapedirs": np.ones((5, 3, 2))})), "-o", str(t / "out.npz")],
    "h5 without the shape groups": lambda t, s: ["model", "import", str(_h5_without_groups(t / "m.h5")), "-o",
                                                 str(t / "out.npz")],
    "npz that is not a model": lambda t, s: ["model", "import", str((np.savez(t / "x.npz", a=np.zeros(3)), t / "x.npz")[1]),
                                             "-o", str(t / "out.npz")],
    "folder that is not ICT": lambda t, s: ["model", "import", str(t), "-o", str(t / "out.npz")],
    "unknown file": lambda t, s: ["model", "import", str(s), "-o", str(t / "out.npz")],
    "output over the input": lambda t, s: ["model", "import", str(_no_landmarks_model(t / "m.npz")), "-o", str(t / "m.npz")],
    "k beyond the identity directions": lambda t, s: [
        "model", "import", str(_pickle(t / "m.pkl", {"v_template": np.eye(3), "f": np.array([[0, 1, 2]]),
                                                     "shapedirs": np.ones((3, 3, 2))})), "--k", "5", "-o", str(t / "out.npz")],
    "import region of a non-ICT model": lambda t, s: ["model", "import", str(_no_landmarks_model(t / "m.npz")), "--region",
                                                      "face", "-o", str(t / "out.npz")],
    "masks outside the model": lambda t, s: ["model", "import", str(_no_landmarks_model(t / "m.npz")), "--masks",
                                             str(write_flame_masks(t / "masks.pkl", {"face": np.array([10**6])})),
                                             "-o", str(t / "out.npz")],
    "landmark indices outside the model": lambda t, s: ["model", "import", str(_no_landmarks_model(t / "m.npz")),
                                                        "--landmarks", str((t / "l.txt").write_text("1 2 99999") and t / "l.txt"),
                                                        "-o", str(t / "out.npz")],
    "light layout's face count beyond the model": lambda t, s: [
        "model", "import", str(_light_layout_model(t / "m.npz", 10**6)), "-o", str(t / "out.npz")],
    "light layout's face count not a number": lambda t, s: [
        "model", "import", str(_light_layout_model(t / "m.npz", np.array([1.5, 2]))), "-o", str(t / "out.npz")],
    "light layout's landmarks not whole numbers": lambda t, s: [
        "model", "import", str(_light_layout_model(t / "m.npz", landmarks=np.array([0.5, 1.2, 2.0]))), "-o",
        str(t / "out.npz")],
    "malicious pickle imported": lambda t, s: ["model", "import", str(_malicious(t / "evil.pkl")), "-o", str(t / "out.npz")],
    "malicious pickle as --model": lambda t, s: ["register", str(s), "--model", str(_malicious(t / "evil.pkl")),
                                                 "-o", str(t / "fit.ply")],
    "malicious pickle in model info": lambda t, s: ["model", "info", str(_malicious(t / "evil.pkl"))],
    "build of different vertex counts": lambda t, s: [
        "model", "build", str(_tetra(t, "a.ply", [[0, 1, 2], [0, 2, 3]])), str(_ply(t / "b.ply", np.eye(3), np.array([[0, 1, 2]]))),
        "-o", str(t / "out.npz")],
    "build of different faces": lambda t, s: [
        "model", "build", str(_tetra(t, "a.ply", [[0, 1, 2], [0, 2, 3]])), str(_tetra(t, "b.ply", [[0, 1, 3], [1, 2, 3]])),
        "-o", str(t / "out.npz")],
    "build of one mesh": lambda t, s: ["model", "build", str(_tetra(t, "a.ply", [[0, 1, 2], [0, 2, 3]])), "-o",
                                       str(t / "out.npz")],
    "sample with a negative sigma": lambda t, s: ["model", "sample", "--sigma", "-1", "-o", str(t / "out.ply")],
    "unknown region": lambda t, s: ["register", str(s), "--region", "nose", "-o", str(t / "fit.ply")],
    "eval region without model": lambda t, s: ["eval", str(s.parent / "gt.ply"), str(s.parent / "gt.ply"), "--region", "face"],
    "landmark count differs": lambda t, s: ["register", str(s), "--landmarks",
                                            str((np.savetxt(t / "l.txt", np.zeros((3, 3))), t / "l.txt")[1]), "-o", str(t / "fit.ply")],
    "landmarks not numbers": lambda t, s: ["register", str(s), "--landmarks",
                                           str((t / "l.txt").write_text("a b c\n") and t / "l.txt"), "-o", str(t / "fit.ply")],
    "model without landmarks": lambda t, s: ["register", str(s), "--model", str(_no_landmarks_model(t / "m.npz")),
                                             "--landmarks", str((np.savetxt(t / "l.txt", np.zeros((10, 3))), t / "l.txt")[1]),
                                             "-o", str(t / "fit.ply")],
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_input_gives_one_line_and_exit_2(case, scan_files, tmp_path, capsys):
    scan, _ = scan_files
    argv = BAD_INPUTS[case](tmp_path, scan)
    before = {p: p.read_bytes() for p in [scan, *tmp_path.rglob("*")] if p.is_file()}
    code, _, err = run(argv + ["-q"] * (argv[0] == "register"), capsys)
    assert code == 2, err
    assert err.startswith("statfit: error: ") and err.count("\n") == 1, err
    assert {p: p.read_bytes() for p in [scan, *tmp_path.rglob("*")] if p.is_file()} == before  # nothing written or changed
    assert not (tmp_path / "pwned").exists()


def test_a_cluttered_scan_under_a_model_without_a_face_says_how_to_keep_the_fit_to_the_face(tmp_path, capsys,
                                                                                         embedded_model):
    """A model with neither landmarks nor a face region cannot keep a cluttered scan's fit to the
    face (ICT's people under clutter 2: 5.25 mm on the face without, 1.41 with; docs/studies.md §42):
    register says so in one line when the pose search finds the clutter, and only then."""
    from statfit.synth.scanner import realistic_scan

    bare = tmp_path / "bare.npz"
    arrays = model_arrays(embedded_model)
    np.savez(bare, **{k: v for k, v in arrays.items() if k != "landmarks" and not k.startswith("region_")})
    for clutter in (2.0, 0.0):
        rng = np.random.default_rng(1)
        made = realistic_scan(embedded_model.sample(rng, 1.0), embedded_model.faces, rng, 1500, clutter=clutter)
        scan = tmp_path / f"scan{clutter}.ply"
        trimesh.Trimesh(made.vertices, made.faces, process=False).export(scan)
        for model in (bare, default_model_path()) if clutter else (bare,):   # no face, no clutter: no line
            code, _, err = run(["register", str(scan), "--model", str(model), "-o", str(tmp_path / "fit.ply"), *FAST],
                               capsys)
            assert code == 0, err
            warned = [line for line in err.splitlines() if "neither landmarks nor a face region" in line]
            assert len(warned) == (clutter > 0 and model == bare), (clutter, model, err)
