"""Full bodies: the MakeHuman reader and body model builder (on the real CC0 files in ../shared),
held-out bodies, and `model build-makehuman` → `synth body` → `synth normals --shape` → `render`."""
from __future__ import annotations

import gzip
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from statfit.geometry.align import umeyama
from statfit.errors import StatfitError
from statfit.model.importers.makehuman import MAX_FILE_BYTES, read_makehuman
from statfit.model.importers.makehuman_shapes import MACRO_CORNERS, BodySpace, _hat_weights, body_regions, build_body_model
from statfit.io.mesh import read_mesh
from statfit.model.statmodel import load_model
from test_cli import run

from common import MAKEHUMAN, ROOT

needs_data = pytest.mark.skipif(not (MAKEHUMAN / "3dobjs").is_dir(), reason=f"MakeHuman data not found at {MAKEHUMAN}")


@pytest.fixture(scope="module")
def space():
    if not (MAKEHUMAN / "3dobjs").is_dir():
        pytest.skip(f"MakeHuman data not found at {MAKEHUMAN}")
    return BodySpace(read_makehuman(MAKEHUMAN))


@pytest.fixture(scope="module")
def study_model(tmp_path_factory):
    """The body study's model (`model build-makehuman`'s defaults: 300 modes, 5,000 bodies, seed 0),
    built once; the study's code, in this process and in workers spawned meanwhile, finds it
    through STATFIT_BODY_MODEL."""
    if not (MAKEHUMAN / "3dobjs").is_dir():
        pytest.skip(f"MakeHuman data not found at {MAKEHUMAN}")
    path = tmp_path_factory.mktemp("body") / "body.npz"
    subprocess.run([sys.executable, "-m", "statfit_cli.main", "model", "build-makehuman", str(MAKEHUMAN), "-o",
                    str(path)], check=True, capture_output=True)
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("STATFIT_BODY_MODEL", str(path))
        # The held-out bodies the tests fit, made once here: each fit's process then reads its body.
        subprocess.run([sys.executable, "-c", "import study_body; [study_body.held_out_body(seed) for seed in (2, 4)]"],
                       check=True, capture_output=True, cwd=ROOT / "studies")
        yield path


def in_span_error(model, vertices: np.ndarray) -> float:
    """Mean vertex distance (m) of ``vertices`` from their projection onto the model's span."""
    delta = (vertices - model.template).reshape(-1)
    projected = model.template.reshape(-1) + model.basis @ (model.basis.T @ delta)
    return float(np.linalg.norm((projected - vertices.reshape(-1)).reshape(-1, 3), axis=1).mean())


def test_macro_weights_are_makehumans_interpolation():
    # MakeHuman's age rule: child → young between 0.1875 and 0.5; an unnamed average corner weighs nothing.
    age = _hat_weights(np.array([0.0, 0.25, 0.5, 0.75, 1.0]), MACRO_CORNERS["age"])
    np.testing.assert_allclose(age[1], [0, 1 - 0.0625 / 0.3125, 0.0625 / 0.3125, 0])
    np.testing.assert_allclose(age[3], [0, 0, 0.5, 0.5])
    np.testing.assert_allclose(age.sum(axis=1), 1.0)
    height = _hat_weights(np.array([0.2, 0.5, 0.9]), MACRO_CORNERS["height"])
    np.testing.assert_allclose(height, [[0.6, 0.4, 0], [0, 1, 0], [0, 0.2, 0.8]])


def test_a_folder_of_another_layout_is_refused(tmp_path, capsys):
    (tmp_path / "targets").mkdir()
    out = tmp_path / "body.npz"
    code, _, err = run(["model", "build-makehuman", str(tmp_path), "-o", str(out)], capsys)
    assert code == 2 and "is not a MakeHuman data folder" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def _one_triangle_folder(folder: Path, targets: dict[str, bytes]) -> Path:
    """A MakeHuman folder of one body triangle and the given macrodetails targets (name → text)."""
    for part in ("3dobjs", "targets/macrodetails", "mesh_metadata"):
        (folder / part).mkdir(parents=True)
    (folder / "mesh_metadata/basemesh_vertex_groups.json").write_text(json.dumps({"body": [[0, 2]]}))
    (folder / "targets/target.json").write_text("{}")
    (folder / "3dobjs/base.obj.gz").write_bytes(gzip.compress(b"v 0 0 0\nv 1 0 0\nv 0 1 0\ng body\nf 1 2 3\n"))
    for name, text in targets.items():
        (folder / f"targets/macrodetails/{name}.target.gz").write_bytes(gzip.compress(text))
    return folder


def test_a_decompression_bomb_is_refused_after_the_cap(tmp_path):
    _one_triangle_folder(tmp_path, {})
    with gzip.open(tmp_path / "targets/macrodetails/bomb.target.gz", "wb", compresslevel=1) as handle:
        handle.write(b"0" * (MAX_FILE_BYTES + 2))
    with pytest.raises(StatfitError, match="decompresses to more than"):
        read_makehuman(tmp_path)


def test_targets_are_read_to_the_digit_and_a_malformed_one_is_refused(tmp_path):
    # comments, blank lines, a vertex beyond the body (dropped) and a target that moves nothing
    good = {"grow": b"# made by hand\n0 1 -.5 2e-1\n\n  2 0 0 -3\n7 1 1 1\n", "empty": b"# nothing\n"}
    seen = []
    data = read_makehuman(_one_triangle_folder(tmp_path / "good", good), lambda done, total: seen.append((done, total)))
    assert seen == [(1, 2), (2, 2)]  # progress: after each target file
    assert list(data.targets) == ["macrodetails/grow"]
    np.testing.assert_array_equal(data.targets["macrodetails/grow"].indices, [0, 2])
    np.testing.assert_allclose(data.targets["macrodetails/grow"].deltas, [[0.1, -0.05, 0.02], [0, 0, -0.3]])
    for name, text in {"three": b"0 1 2\n1 1 2\n", "word": b"0 1 x 2\n", "ragged": b"0 1 2 3\n1 1 2\n",
                       "negative": b"-1 0 0 0\n", "nan": b"0 nan 0 0\n"}.items():
        with pytest.raises(StatfitError, match=f"{name}.target.gz") as refused:
            read_makehuman(_one_triangle_folder(tmp_path / name, {name: text}))
        assert "\n" not in str(refused.value)


@needs_data
def test_the_skin_is_a_closed_consistent_surface_in_metres(space):
    vertices, faces = space.data.vertices, space.data.faces
    assert vertices.shape == (13380, 3) and faces.shape == (26756, 3)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert 1.5 < np.ptp(vertices[:, 1]) < 2.0  # a standing adult, in metres
    regions = body_regions(space)
    assert {"head", "arms", "legs", "torso", "left", "right"} <= set(regions)
    assert vertices[regions["head"], 1].mean() > vertices[regions["torso"], 1].mean() > vertices[regions["legs"], 1].mean()
    assert (vertices[regions["left"], 0] > 0).all() and (vertices[regions["right"], 0] < 0).all()


@needs_data
def test_the_model_reproduces_fresh_bodies_and_not_held_out_ones(space):
    built = build_body_model(space, 200, 1000, seed=0)
    model = built.model
    mesh = trimesh.Trimesh(model.template, model.faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert np.all(np.diff(built.variance_explained) >= 0) and built.variance_explained[-1] > 0.999
    fresh = space.shapes(space.weights(np.random.default_rng(99), 4, "train"))
    held_out = space.shapes(space.weights(np.random.default_rng(99), 4, "held_out"))
    fresh_errors = [in_span_error(model, body) for body in fresh]
    held_out_errors = [in_span_error(model, body) for body in held_out]
    assert max(fresh_errors) < 0.0005  # bodies from the training distribution: within 0.5 mm on average
    assert min(held_out_errors) > 5 * max(fresh_errors)  # held-out bodies lie outside the span
    # the same seed builds the same model
    again = build_body_model(space, 200, 1000, seed=0).model
    np.testing.assert_array_equal(again.basis, model.basis)


@needs_data
def test_a_body_from_one_normal_map_on_the_command_line(tmp_path, capsys):
    model, person, exr, camera, fit, gt = (tmp_path / name for name in
                                           ("body.npz", "person.ply", "body.exr", "cam.json", "fit.ply", "gt.ply"))
    code, out, err = run(["model", "build-makehuman", str(MAKEHUMAN), "-o", str(model), "--k", "40",
                          "--samples", "400", "--json"], capsys)
    assert code == 0, err
    assert json.loads(out)["modes"] == 40 and load_model(model).num_vertices == 13380
    assert "learning 40 modes from 400 random bodies" in err  # progress on stderr; stdout is the JSON alone
    assert run(["synth", "body", str(MAKEHUMAN), "--seed", "4", "-o", str(person)], capsys)[0] == 0
    code, _, err = run(["synth", "normals", "--model", str(model), "--shape", str(person), "--yaw", "30",
                        "--size", "160", "--out", str(exr), "--camera-out", str(camera), "--gt", str(gt)], capsys)
    assert code == 0, err
    code, _, err = run(["render", str(exr), "--camera", str(camera), "--model", str(model), "--out", str(fit),
                        "--iterations", "150", "-q"], capsys)
    assert code == 0, err
    fitted, truth, template = read_mesh(fit)[0], read_mesh(gt)[0], load_model(model).template
    aligned = lambda shape: umeyama(shape, truth, with_scale=True).apply(shape)  # noqa: E731
    error = lambda shape: np.linalg.norm(aligned(shape) - truth, axis=1).mean()  # noqa: E731
    assert error(fitted) < 0.8 * error(template)  # 150 iterations of a 40-mode model at 160 px
    # a mesh of another topology is refused
    sphere = tmp_path / "sphere.ply"
    trimesh.creation.icosphere().export(sphere)
    code, _, err = run(["synth", "normals", "--model", str(model), "--shape", str(sphere),
                        "--out", str(tmp_path / "x.exr")], capsys)
    assert code == 2 and "not in the model's topology" in err and not (tmp_path / "x.exr").exists()


def _study_fit(method: str, yaw: float, size: int, iterations: int | None = None, seed: int = 4,
               align_shape_lr: float | None = None, also_at: tuple[int, ...] = ()) -> dict:
    """The body study's row of one fit of held-out body ``seed`` from ``yaw`` (pitch 10°)."""
    import torch

    sys.path.insert(0, str(ROOT / "studies"))
    import study_body

    torch.set_num_threads(1)
    return study_body.run_case((seed, yaw, 10.0, method, size), iterations, align_shape_lr, also_at)


@pytest.mark.slow
@needs_data
def test_the_alignment_fits_a_small_bodys_size(study_model):
    """Body 2, the study's smallest (1.21 m; the model's mean 1.74), from the front at 160²: after
    the rigid alignment (and one iteration) the fit is 2× closer to the truth, size and place
    included, with the coefficients at their own step than at the pose's (measured 50 against
    106 mm): at the pose's step no coefficient moves more than ~2 standard deviations in the
    alignment's 200 steps (docs/studies.md §13)."""
    from conftest import run_two_at_a_time

    raw = {name: row["raw"]["all"] for name, row in run_two_at_a_time(_study_fit, {
        "shipped": ("default", 30.0, 160, 1, 2), "pose's step": ("default", 30.0, 160, 1, 2, 0.01)}).items()}
    assert raw["shipped"] < 0.6 * raw["pose's step"], raw


@pytest.fixture(scope="module")
def study_fits(study_model) -> dict[str, dict]:
    """The slow body tests' fits of body 4 from the front (yaw 30°) at 160², two at a time (the
    longest first): `laplacian` at its own 3,000 iterations, and at 1,000 (its snapshot there: its
    step is constant, so a 1,000-iteration fit ends there to the bit); the default; `statistical` at
    1,000 iterations."""
    from conftest import run_two_at_a_time

    fits = run_two_at_a_time(_study_fit, {"laplacian": ("laplacian", 30.0, 160, None, 4, None, (1000,)),
                                          "default": ("default", 30.0, 160),
                                          "statistical 1000": ("statistical", 30.0, 160, 1000)})
    return fits | {"laplacian 1000": fits["laplacian"]["at"][1000]}


@pytest.mark.slow
@needs_data
def test_the_statistical_filter_keeps_the_unseen_side_plausible(study_fits):
    """The paper's body claim, on a body the model never saw: the Laplacian filter fits the visible
    side and bends the unseen one; the statistical filter keeps it close to a body's shape (mean
    normal angle on the unseen side; study: 7.2° vs 11.9° over 12 fits at 384² and 3000 iterations; at
    the 160² and 1000 iterations used here to keep the suite short, 8.1° vs 11.6°)."""
    angles = {m: study_fits[f"{m} 1000"]["normal_angle_unseen_deg"] for m in ("statistical", "laplacian")}
    assert angles["statistical"] < 0.75 * angles["laplacian"], angles


@pytest.mark.slow
@needs_data
def test_the_default_is_closer_than_laplacian_seen_and_unseen(study_fits):
    """Issue 14's target on one of its bodies: the render default (two hybrid stages, then the
    Laplacian filter, from the alignment's fitted coefficients) is closer to the truth than
    `laplacian` at its own tuned setting, over all vertices and over those the map does not show
    (study: lower on all six bodies, 10.2 mm against 10.8, 0.94×; docs/studies.md §13). Here, at
    160², measured 2026-11-28: 20.1 against 22.0 and 21.2 against 23.1 mm (0.92×); with
    OMP_NUM_THREADS=1 the model's randomised SVD sums in another order and the fits end elsewhere:
    11.8 against 12.5 and 12.6 against 13.2 (0.94–0.95×). So the bound is the study's claim, lower,
    not a margin tighter than the study's own mean gap."""
    default, laplacian = study_fits["default"]["aligned"], study_fits["laplacian"]["aligned"]
    assert default["all"] < laplacian["all"], (default, laplacian)
    assert default["unseen"] < laplacian["unseen"], (default, laplacian)
