"""Model importers (FLAME/SMPL-X pickles and npz, ICT-FaceKit folders, BFM 2017 h5), the restricted
unpickler, the import cache, and PCA model building — on files written in each format's real layout."""
from __future__ import annotations

import os
import pickle

import numpy as np
import pytest
import scipy.sparse

from model_files import (random_smpl_arrays, write_bfm_h5, write_flame_masks, write_flame_pickle, write_ict_folder,
                         write_obj)
from statfit.model.build import build_model
from statfit.errors import StatfitError
from statfit.model.importers import cache, ict, import_model
from statfit.model.importers.safe_pickle import load_pickle
from statfit.model.statmodel import load_model, save_model, units_guess
from conftest import ICT_DIR


def assert_same_distribution(model, shapedirs: np.ndarray, rtol: float = 1e-6) -> None:
    """The model's covariance U diag(std²) Uᵀ equals S Sᵀ for S = shapedirs (N, 3, K) flattened,
    compared on random probe vectors (the full 3N × 3N matrices need not be formed)."""
    flat = shapedirs.reshape(-1, shapedirs.shape[2])
    probes = np.random.default_rng(0).standard_normal((flat.shape[0], 4))
    scaled = model.basis * model.std
    expected = flat @ (flat.T @ probes)
    np.testing.assert_allclose(scaled @ (scaled.T @ probes), expected, rtol=rtol, atol=rtol * np.abs(expected).max())


@pytest.fixture
def smpl_arrays(rng):
    return random_smpl_arrays(rng)


@pytest.mark.parametrize("style", ["2020", "2020-py2", "2023"])
def test_flame_pickle_keeps_identity_and_optionally_expression(tmp_path, smpl_arrays, style):
    path = write_flame_pickle(tmp_path / "generic_model.pkl", smpl_arrays, style)
    assert (b"chumpy.ch\nCh\n" in path.read_bytes()) == (style != "2023")
    assert (b"_codecs" in path.read_bytes()) == (style == "2020")
    identity = import_model(path)
    np.testing.assert_array_equal(identity.template, smpl_arrays["v_template"])
    np.testing.assert_array_equal(identity.faces, smpl_arrays["f"])
    assert_same_distribution(identity, smpl_arrays["shapedirs"][..., :300])
    assert_same_distribution(import_model(path, expressions=True), smpl_arrays["shapedirs"])
    assert_same_distribution(import_model(path, k=7), smpl_arrays["shapedirs"][..., :7])


@pytest.mark.parametrize("style", ["2020", "2020-py2"])
def test_chumpy_pickle_arrays_and_sparse_matrices_come_back_exactly(tmp_path, smpl_arrays, style):
    loaded = load_pickle(write_flame_pickle(tmp_path / "m.pkl", smpl_arrays, style))
    for key in ("shapedirs", "J", "posedirs", "kintree_table"):
        np.testing.assert_array_equal(loaded[key], smpl_arrays[key])
    assert scipy.sparse.issparse(loaded["J_regressor"])
    np.testing.assert_array_equal(loaded["J_regressor"].toarray(), smpl_arrays["J_regressor"].toarray())
    assert loaded["bs_style"] == "lbs"


class _Exploit:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


@pytest.mark.parametrize("protocol", [0, 2, 5])
def test_a_malicious_pickle_is_refused_and_runs_nothing(tmp_path, protocol):
    marker = tmp_path / "pwned"
    path = tmp_path / "generic_model.pkl"
    path.write_bytes(pickle.dumps({"v_template": _Exploit(marker)}, protocol=protocol))
    with pytest.raises(StatfitError, match="refusing to load .*system"):
        import_model(path)
    assert not marker.exists()


def test_smplx_npz_splits_shape_and_expression(tmp_path, rng):
    arrays = random_smpl_arrays(rng, n=50, k=20)  # SMPL-X v1.0 layout: 10 shape + 10 expression
    arrays.update(hands_componentsl=np.zeros((45, 45)), hands_componentsr=np.zeros((45, 45)))
    np.savez(tmp_path / "SMPLX_NEUTRAL.npz", **{k: v for k, v in arrays.items() if k != "J_regressor"},
             J_regressor=arrays["J_regressor"].toarray(), part2num=np.array({"head": 15}, dtype=object))
    model = import_model(tmp_path / "SMPLX_NEUTRAL.npz")
    assert "SMPL-X" in model.source and model.num_modes == 10
    assert_same_distribution(model, arrays["shapedirs"][..., :10])
    with pytest.raises(StatfitError, match="between 1 and 10.*--expressions"):
        import_model(tmp_path / "SMPLX_NEUTRAL.npz", k=20)
    assert import_model(tmp_path / "SMPLX_NEUTRAL.npz", expressions=True).num_modes == 20


def test_bfm_orthonormal_basis_is_scaled_by_the_standard_deviations(tmp_path, rng):
    n, k = 40, 6
    mean = rng.standard_normal(3 * n) * 50  # millimetres
    basis, _ = np.linalg.qr(rng.standard_normal((3 * n, k)))
    variance = np.linspace(40, 2, k)
    faces = np.stack([np.zeros(n - 2, int), np.arange(1, n - 1), np.arange(2, n)], axis=1)
    path = write_bfm_h5(tmp_path / "model2017-1_bfm_nomouth.h5", mean, basis, variance, faces,
                        expression=(np.linalg.qr(rng.standard_normal((3 * n, 3)))[0], np.ones(3)))
    model = import_model(path)
    np.testing.assert_allclose(model.template, mean.reshape(n, 3), rtol=1e-6)
    np.testing.assert_array_equal(model.faces, faces)
    np.testing.assert_allclose(model.std, np.sqrt(variance), rtol=1e-5)  # orthonormal columns: std = sqrt(var)
    assert_same_distribution(model, (basis * np.sqrt(variance)).reshape(n, 3, k), rtol=1e-5)
    assert import_model(path, expressions=True).num_modes == k + 3


def test_ict_quads_become_two_triangles_and_regions_are_cut(tmp_path, rng, monkeypatch):
    grid = np.array([[x, y, 0.0] for y in range(3) for x in range(3)])  # 3 × 3 vertices, 2 × 2 quads
    quads = np.array([[0, 1, 4, 3], [1, 2, 5, 4], [3, 4, 7, 6], [4, 5, 8, 7]])
    identities = grid + rng.normal(scale=0.01, size=(3, 9, 3))
    folder = write_ict_folder(tmp_path / "FaceXModel", grid, quads, identities)
    monkeypatch.setattr(ict, "REGIONS", {"face": (0, 6), "head": (6, 9), "teeth": (9, 12)})
    model = import_model(folder, region="face+head")
    assert len(model.faces) == 8
    normals = np.cross(*(grid[model.faces[:, 1:]] - grid[model.faces[:, :1]]).transpose(1, 0, 2))
    assert (normals[:, 2] > 0).all()  # the quads' counter-clockwise winding is kept
    assert_same_distribution(model, (identities - grid).transpose(1, 2, 0))
    face_only = import_model(folder, region="face")
    assert face_only.num_vertices == 6 and len(face_only.faces) == 4
    np.testing.assert_array_equal(face_only.regions["face"], np.arange(6))
    with pytest.raises(StatfitError, match="needs vertices up to 12"):
        import_model(folder, region="teeth")
    with pytest.raises(StatfitError, match="unknown ICT region 'nose'"):
        import_model(folder, region="face+nose")


def test_ict_import_matches_the_shared_ict_model(tmp_path, ict_model):
    """OBJs written from ../shared/data/ict-face (neutral + identity_i = neutral + shapedirs_i) import
    back to the same template, faces, directions and face/head regions."""
    with np.load(ICT_DIR / "ict_face_identity.npz") as data:
        template, faces = data["v_template"].astype(np.float64), data["faces"]
        shapedirs, face_count = data["shapedirs"][..., :5].astype(np.float64), int(data["face_vertex_count"])
    folder = write_ict_folder(tmp_path / "FaceXModel", template, faces, (template[None] + shapedirs.transpose(2, 0, 1)))
    model = import_model(folder, region="face+head")
    np.testing.assert_allclose(model.template, template, atol=1e-6)
    np.testing.assert_array_equal(model.faces, faces)
    assert_same_distribution(model, shapedirs, rtol=1e-5)
    np.testing.assert_array_equal(model.regions["face"], np.arange(face_count))
    np.testing.assert_array_equal(model.regions["head"], np.arange(face_count, len(template)))


def test_saved_model_round_trips(tmp_path, embedded_model):
    save_model(embedded_model, tmp_path / "again.npz")
    again = load_model(tmp_path / "again.npz")
    np.testing.assert_array_equal(again.template, embedded_model.template)
    np.testing.assert_array_equal(again.regions["face"], embedded_model.regions["face"])
    np.testing.assert_array_equal(again.landmarks, embedded_model.landmarks)
    np.testing.assert_allclose(again.std, embedded_model.std, rtol=1e-10)
    assert_same_distribution(again, (embedded_model.basis * embedded_model.std).reshape(-1, 3, embedded_model.num_modes))


def test_cache_imports_once_and_rebuilds_a_damaged_entry(tmp_path, smpl_arrays, monkeypatch):
    path = write_flame_pickle(tmp_path / "generic_model.pkl", smpl_arrays)
    first = cache.open_any_model(path, folder=tmp_path / "cache")
    entries = list((tmp_path / "cache" / "models").glob("*.npz"))
    assert len(entries) == 1
    calls = []
    monkeypatch.setattr(cache, "import_model", lambda *a, **kw: calls.append(a) or first)
    assert_same_distribution(cache.open_any_model(path, folder=tmp_path / "cache"),
                             smpl_arrays["shapedirs"][..., :300])
    assert not calls
    entries[0].write_bytes(b"damaged")
    cache.open_any_model(path, folder=tmp_path / "cache")
    assert len(calls) == 1 and load_model(entries[0]).num_modes == first.num_modes
    other = cache.open_any_model(path, folder=tmp_path / "cache", expressions=True)  # other options, other entry
    assert len(list((tmp_path / "cache" / "models").glob("*.npz"))) == 2 and other is first


@pytest.mark.parametrize("randomized", [False, True])
def test_build_recovers_a_known_subspace(rng, randomized):
    n, r, m = 300, 4, 60
    template = rng.standard_normal((n, 3))
    true_basis, _ = np.linalg.qr(rng.standard_normal((3 * n, r)))
    true_std = np.array([5.0, 3.0, 2.0, 1.0]) * 1e-2
    coeffs = rng.standard_normal((m, r))
    faces = np.array([[0, 1, 2], [2, 3, 4]])
    meshes = [((template.reshape(-1) + true_basis @ (true_std * c)).reshape(n, 3), faces) for c in coeffs]
    built = build_model(meshes, r, randomized=randomized)
    cosines = np.linalg.svd(true_basis.T @ built.model.basis, compute_uv=False)
    assert cosines.min() > 1 - 1e-9  # same subspace
    assert built.variance_explained[-1] == pytest.approx(1.0)
    sample_std = np.sqrt(np.linalg.eigvalsh(np.cov((coeffs * true_std).T))[::-1])
    np.testing.assert_allclose(built.model.std, sample_std, rtol=1e-8)
    np.testing.assert_allclose(built.model.template, np.mean([v for v, _ in meshes], axis=0), atol=1e-12)


def test_build_refuses_meshes_of_different_topology(rng):
    vertices = rng.standard_normal((5, 3))
    faces = np.array([[0, 1, 2], [2, 3, 4]])
    with pytest.raises(StatfitError, match="b.ply has 4 vertices"):
        build_model([(vertices, faces), (vertices[:4], faces[:1])], names=["a.ply", "b.ply"])
    with pytest.raises(StatfitError, match="faces of b.ply differ"):
        build_model([(vertices, faces), (vertices, faces[:, ::-1])], names=["a.ply", "b.ply"])


@pytest.mark.parametrize("content,message", [
    (pickle.dumps([1, 2, 3], protocol=2), "not a model pickle .*got a list"),
    (pickle.dumps({"v_template": np.zeros((4, 3))}, protocol=2), "lacks the key"),
    (pickle.dumps({"v_template": np.zeros((4, 3)), "f": np.array([[0, 1, 2]]),
                   "shapedirs": np.zeros((5, 3, 2))}, protocol=2), "does not match v_template"),
    (b"\x80\x02garbage", "not a valid pickle"),
])
def test_wrong_pickles_are_refused(tmp_path, content, message):
    (tmp_path / "m.pkl").write_bytes(content)
    with pytest.raises(StatfitError, match=message):
        import_model(tmp_path / "m.pkl")


def test_obj_reader_keeps_file_order(tmp_path):
    vertices = np.random.default_rng(2).standard_normal((7, 3))
    write_obj(tmp_path / "m.obj", vertices, np.array([[6, 0, 3], [1, 2, 5]]))
    read, faces = ict.read_obj(tmp_path / "m.obj")
    np.testing.assert_allclose(read, vertices, rtol=1e-8)
    np.testing.assert_array_equal(faces, [[6, 0, 3], [1, 2, 5]])


@pytest.mark.parametrize("extent,guess", [(0.25, "metres (head-sized)"), (1.8, "metres (body-sized)"),
                                          (25.0, "centimetres (head-sized)"), (220.0, "millimetres (head-sized)"),
                                          (4.0, "unknown")])
def test_units_guess(extent, guess):
    assert units_guess(np.array([[0.0, 0.0, 0.0], [extent, extent / 2, extent / 3]])) == guess


@pytest.mark.parametrize("kind", ["csr", "coo"])
def test_other_sparse_matrices_in_pickles(tmp_path, kind):
    matrix = scipy.sparse.random(4, 6, density=0.4, format=kind, random_state=1)
    (tmp_path / "m.pkl").write_bytes(pickle.dumps({"J_regressor": matrix}, protocol=2))
    np.testing.assert_array_equal(load_pickle(tmp_path / "m.pkl")["J_regressor"].toarray(), matrix.toarray())


@pytest.mark.parametrize("text,message", [("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", "does not exist"),
                                          ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n", "not an integer"),
                                          ("v 0 0\nf 1 2 3\n", "not three numbers"),
                                          ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", "face with 2 vertices")])
def test_broken_ict_meshes_are_refused(tmp_path, text, message):
    (tmp_path / "generic_neutral_mesh.obj").write_text(text)
    with pytest.raises(StatfitError, match=message):
        import_model(tmp_path)


def _grid_sources(folder, rng, smpl_arrays) -> dict:
    """One small model file per format; the ICT folder is a 3 × 3 quad grid."""
    grid = np.array([[x, y, 0.0] for y in range(3) for x in range(3)])
    quads = np.array([[0, 1, 4, 3], [1, 2, 5, 4], [3, 4, 7, 6], [4, 5, 8, 7]])
    basis, _ = np.linalg.qr(rng.standard_normal((27, 3)))
    return {"flame": lambda: write_flame_pickle(folder / "generic_model.pkl", smpl_arrays),
            "bfm": lambda: write_bfm_h5(folder / "bfm.h5", grid.reshape(-1), basis, np.array([3.0, 2.0, 1.0]), quads[:, :3]),
            "ict": lambda: write_ict_folder(folder / "FaceXModel", grid, quads, grid + rng.normal(size=(2, 9, 3)))}


@pytest.mark.parametrize("kind", ["flame", "bfm", "ict"])
def test_every_format_round_trips_through_the_npz_contract(tmp_path, rng, smpl_arrays, monkeypatch, kind):
    """Imported, saved and loaded again: same template, faces, regions and shape distribution."""
    monkeypatch.setattr(ict, "REGIONS", {"face": (0, 6), "head": (6, 9)})  # ranges of the small grid
    model = import_model(_grid_sources(tmp_path, rng, smpl_arrays)[kind]())
    save_model(model, tmp_path / "model.npz")
    again = load_model(tmp_path / "model.npz")
    np.testing.assert_array_equal(again.template, model.template)
    np.testing.assert_array_equal(again.faces, model.faces)
    assert again.regions.keys() == model.regions.keys()
    assert_same_distribution(again, (model.basis * model.std).reshape(model.num_vertices, 3, -1))


def test_flame_masks_become_regions(tmp_path, smpl_arrays):
    masks = {"face": np.arange(10, 40), "lips": np.array([12, 13, 14])}
    model = import_model(write_flame_pickle(tmp_path / "generic_model.pkl", smpl_arrays),
                         masks=write_flame_masks(tmp_path / "FLAME_masks.pkl", masks))
    assert model.regions.keys() == masks.keys()
    for name, index in masks.items():
        np.testing.assert_array_equal(model.regions[name], index)


@pytest.mark.parametrize("masks,message", [({"face": np.array([0, 60])}, "face must be vertex indices in"),
                                           ({"face/x": np.array([0])}, "letters, digits"),
                                           ([np.arange(3)], "expected a dict")])
def test_bad_masks_are_refused(tmp_path, smpl_arrays, masks, message):
    model = write_flame_pickle(tmp_path / "generic_model.pkl", smpl_arrays)
    with pytest.raises(StatfitError, match=message):
        import_model(model, masks=write_flame_masks(tmp_path / "FLAME_masks.pkl", masks))


def test_landmark_indices_are_stored(tmp_path, smpl_arrays):
    (tmp_path / "lmk.txt").write_text("# FLAME landmark vertices\n3 17, 42\n59\n")
    model = import_model(write_flame_pickle(tmp_path / "generic_model.pkl", smpl_arrays), landmarks=tmp_path / "lmk.txt")
    np.testing.assert_array_equal(model.landmarks, [3, 17, 42, 59])
    for text, message in (("3 60\n", r"must be vertex indices in \[0, 60\)"), ("3 -1\n", "non-negative integers")):
        (tmp_path / "lmk.txt").write_text(text)
        with pytest.raises(StatfitError, match=message):
            import_model(tmp_path / "generic_model.pkl", landmarks=tmp_path / "lmk.txt")
