"""Landmarks: the file formats, the robust start, and the landmark term (its value in closed
form, its Gauss–Newton residuals against autograd, its pull on a fit)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from statfit.geometry.align import Similarity
from statfit.errors import StatfitError
from statfit.io.landmarks import MAX_LANDMARK_BYTES, read_landmarks
from statfit.objectives.landmarks import LandmarkObjective
from statfit.registration.prealign import landmark_alignment
from scipy.spatial.transform import Rotation


@pytest.mark.parametrize("name, text", [
    ("l.txt", "1 2 3\nnan nan nan\n4 5 6\n"),
    ("l.pts", "version: 1\nn_points: 3\n{\n1 2 3\nnan nan nan\n4 5 6\n}\n"),
    ("l.json", "[[1, 2, 3], null, [4, 5, 6]]"),
])
def test_every_format_reads_the_same_points(tmp_path, name, text):
    (tmp_path / name).write_text(text)
    np.testing.assert_array_equal(read_landmarks(tmp_path / name), [[1, 2, 3], [np.nan] * 3, [4, 5, 6]])


@pytest.mark.parametrize("name, text, message", [
    ("a.pts", "version: 1\nn_points: 2\n{\n1 2\n3 4\n}\n", "2D landmarks"),
    ("b.pts", "version: 1\nn_points: 3\n{\n1 2 3\n}\n", "n_points says 3"),
    ("c.pts", "1 2 3\n", "between { and }"),
    ("d.json", "{\"x\": 1}", "JSON list"),
    ("e.json", "[[1, 2, \"z\"]]", "JSON list"),
    ("f.json", "[[1, 2", "not JSON"),
    ("g.txt", "1 2\n", "three numbers"),
])
def test_bad_landmark_files_are_one_line_errors(tmp_path, name, text, message):
    (tmp_path / name).write_text(text)
    with pytest.raises(StatfitError, match=message):
        read_landmarks(tmp_path / name)


def test_a_huge_landmark_file_is_refused_by_its_size(tmp_path):
    with open(tmp_path / "huge.txt", "wb") as handle:
        handle.truncate(MAX_LANDMARK_BYTES + 1)
    with pytest.raises(StatfitError, match="too large"):
        read_landmarks(tmp_path / "huge.txt")


def test_one_misplaced_landmark_does_not_move_the_start(embedded_model):
    truth = Similarity(10.0, Rotation.from_euler("xyz", [40, -70, 20], degrees=True).as_matrix(),
                       np.array([5.0, -300.0, 80.0]))
    landmarks = truth.apply(embedded_model.template[embedded_model.landmarks])
    landmarks[3] += [0.0, 0.0, 10.0 * np.ptp(embedded_model.template[:, 2])]  # one landmark a head's depth away
    found = landmark_alignment(embedded_model, landmarks)
    assert abs(found.scale - 10.0) < 1e-3 and np.abs(found.rotation - truth.rotation).max() < 1e-4
    np.testing.assert_allclose(found.translation, truth.translation, atol=1e-2)


def test_the_term_is_geman_mcclure_and_gauss_newton_sees_its_gradient():
    torch.manual_seed(0)
    vertices = torch.randn(40, 3, dtype=torch.float64)
    indices = torch.tensor([1, 5, 7, 30])
    targets = vertices[indices] + torch.tensor([[0.01, 0, 0], [0, 0.02, 0], [0, 0, 0.5], [0.03, 0, 0.04]],
                                               dtype=torch.float64)
    term = LandmarkObjective(indices, targets, weight=2.0, scale=0.05)
    d2 = torch.tensor([0.01**2, 0.02**2, 0.5**2, 0.05**2], dtype=torch.float64)
    expected = 2.0 * (0.05**2 * d2 / (0.05**2 + d2)).mean()
    assert float(term(vertices)["landmarks"]) == pytest.approx(float(expected), rel=1e-12)
    # Gauss–Newton: ∇_c Σ r² at the refresh = ∇_c (per · term) for x = x0 + D c.
    directions = torch.randn(40, 3, 6, dtype=torch.float64)
    coefficients = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    moved = vertices + directions @ coefficients
    per = 17.0
    (per * term(moved)["landmarks"]).backward()
    term.refresh(vertices)
    residuals = term.residuals(vertices, per)
    gauss_newton = 2 * term.jacobian(directions, per).T @ residuals
    torch.testing.assert_close(gauss_newton, coefficients.grad, rtol=1e-10, atol=1e-12)
    # The far landmark (10 scales away) pulls ~1000x less than the near ones.
    pull = torch.autograd.functional.jacobian(lambda x: term(x)["landmarks"], vertices)[indices].norm(dim=1)
    assert pull[2] < 1e-2 * pull[1]


@pytest.mark.parametrize("seed", [0, 2])
def test_the_landmark_term_holds_the_landmarks_where_the_start_alone_drifts(embedded_model, tmp_path, seed):
    """Off the model's span (fitted with 10 of 50 modes), one landmark misplaced by half the head:
    with the term the other landmarks end ≤ 0.5x as far from the truth as with the start only."""
    from conftest import run_cli
    from statfit.io.mesh import points_bytes
    from statfit.core.methods import LANDMARK_WEIGHT
    from statfit.registration.job import register
    from statfit.synth.sample import sample_target, scan_from_view

    rng = np.random.default_rng(seed)
    target = sample_target(embedded_model, rng, 1.5)
    points = scan_from_view(target, embedded_model.faces, rng, 3000, 30.0)
    landmarks = target[embedded_model.landmarks].copy()
    landmarks[0] += 0.5 * np.ptp(embedded_model.template, axis=0)
    small = embedded_model.truncated(10)
    errors = {}
    for weight in (0.0, LANDMARK_WEIGHT):
        fit = register(small, points, "default", landmarks=landmarks, landmark_weight=weight, iterations=400,
                       align="none")     # the landmark similarity alone places both: the term is what differs
        errors[weight] = (np.linalg.norm(fit.vertices[small.landmarks][1:] - landmarks[1:], axis=1).mean(),
                          np.linalg.norm(fit.vertices - target, axis=1).mean())
    assert errors[LANDMARK_WEIGHT][0] <= 0.5 * errors[0.0][0], errors
    assert errors[LANDMARK_WEIGHT][1] <= 1.1 * errors[0.0][1], errors
    # The same from the command line, with the landmarks as an iBUG .pts file.
    (tmp_path / "scan.ply").write_bytes(points_bytes(points))
    rows = "\n".join(" ".join(f"{v:.9g}" for v in row) for row in landmarks)
    (tmp_path / "l.pts").write_text(f"version: 1\nn_points: {len(landmarks)}\n{{\n{rows}\n}}\n")
    code, err = run_cli(["register", str(tmp_path / "scan.ply"), "--landmarks", str(tmp_path / "l.pts"),
                         "--landmark-weight", "10", "--iterations", "40", "-q", "--out", str(tmp_path / "fit.ply")])
    assert code == 0, err


def test_each_method_weighs_its_landmarks_with_its_own_default(embedded_model, tmp_path):
    """pca's term weighs 1 (its span is all it moves; docs/studies.md §12), the default pipeline's
    10: ``landmark_weight=None`` gives exactly the fit with the method's weight, and the log
    records the weight used."""
    import json

    from conftest import run_cli
    from statfit.io.mesh import points_bytes
    from statfit.core.methods import LANDMARK_WEIGHT, landmark_weight
    from statfit.registration.job import register
    from statfit.synth.sample import sample_target, scan_from_view

    assert (landmark_weight("pca"), landmark_weight("default"), LANDMARK_WEIGHT) == (1.0, 10.0, 10.0)
    rng = np.random.default_rng(5)
    target = sample_target(embedded_model, rng, 1.0)
    points = scan_from_view(target, embedded_model.faces, rng, 2000, 0.0)
    landmarks = target[embedded_model.landmarks] + rng.normal(scale=0.02, size=(len(embedded_model.landmarks), 3))
    fits = {w: register(embedded_model, points, "pca", landmarks=landmarks, landmark_weight=w, align="none").vertices
            for w in (None, 1.0, 10.0)}
    assert np.array_equal(fits[None], fits[1.0])
    assert not np.allclose(fits[None], fits[10.0])
    (tmp_path / "scan.ply").write_bytes(points_bytes(points))
    np.savetxt(tmp_path / "l.txt", landmarks)
    for method, weight in (("pca", 1.0), ("default", 10.0)):
        log = tmp_path / f"{method}.jsonl"
        code, err = run_cli(["register", str(tmp_path / "scan.ply"), "--method", method, "--landmarks",
                             str(tmp_path / "l.txt"), "--iterations", "20", "-q", "--log", str(log),
                             "--out", str(tmp_path / f"{method}.ply")])
        assert code == 0, err
        assert json.loads(log.read_text().splitlines()[0])["landmark_weight"] == weight


@pytest.mark.parametrize("seed", [1, 3])
def test_landmarks_on_half_a_face_place_a_start_the_scan_then_corrects(embedded_model, seed):
    """Noisy landmarks on one half tilt their similarity by degrees and scale it by several per cent
    (an independent truth: the pose the scan was made in); the polish on the scan undoes both."""
    from statfit.registration.pose.search import refine_pose
    from statfit.structures.scan import Scan
    from statfit.synth.sample import scan_from_view

    model = embedded_model
    rng = np.random.default_rng(seed)
    target = model.sample(rng)
    truth = Similarity(10.0, Rotation.from_rotvec(rng.normal(size=3)).as_matrix(), rng.normal(size=3) * 100)
    points = scan_from_view(target, model.faces, rng, 3000, 0.0)
    landmarks = target[model.landmarks] + rng.normal(scale=0.01 * np.ptp(model.template[:, 0]),
                                                     size=(model.landmarks.size, 3))
    middle = landmarks[:, 0].mean()
    landmarks[landmarks[:, 0] < middle] = np.nan
    scan = Scan.from_points(truth.apply(points[points[:, 0] > middle]))
    start = landmark_alignment(model, truth.apply(landmarks))
    refined = refine_pose(model, scan, start).transform

    def degrees(rotation: np.ndarray) -> float:
        return float(np.degrees(Rotation.from_matrix(rotation.T @ truth.rotation).magnitude()))

    assert degrees(start.rotation) > 2.0 and abs(start.scale - 10.0) > 0.2     # the case is a hard one
    assert degrees(refined.rotation) < 0.6
    assert refined.scale == 10.0



def test_a_stage_without_landmarks_fits_the_scan_alone(embedded_model):
    """``landmarks=False``: the closed-form stage ignores the landmark term (the result is the fit
    with the landmarks placing the start only, weight 0, exactly); with True it fits them."""
    import importlib
    from dataclasses import replace

    from statfit.core.methods import resolve

    register = importlib.import_module("statfit.registration.job").register
    rng = np.random.default_rng(5)
    from statfit.synth.sample import sample_target, scan_from_view

    target = sample_target(embedded_model, rng, 1.0)
    points = scan_from_view(target, embedded_model.faces, rng, 2000, 20.0)
    landmarks = target[embedded_model.landmarks] + 0.05 * np.ptp(embedded_model.template, axis=0)  # all off
    closed_form = replace(resolve("pca")[0], landmarks=False)
    plain = register(embedded_model, points, stages=(closed_form,), landmarks=landmarks, landmark_weight=0.0,
                     align="none")
    ignored = register(embedded_model, points, stages=(closed_form,), landmarks=landmarks, align="none")
    fitted = register(embedded_model, points, stages=(replace(closed_form, landmarks=True),), landmarks=landmarks,
                      align="none")
    np.testing.assert_array_equal(ignored.vertices, plain.vertices)
    assert not np.allclose(fitted.vertices, plain.vertices, atol=1e-4)
