"""Inverse rendering in the library: frames, the objective, pose alignment, reconstruct()."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from statfit.geometry.align import Similarity
from statfit.structures.camera import Camera
from statfit.errors import StatfitError
from statfit.structures.frame import Frame
from statfit.core.pose import camera_in_frame
from statfit.render.job import camera_space_normals, downsampled, reconstruct
from statfit.structures.normal_map import NormalMap
from statfit.objectives.normals import NormalMapObjective
from statfit.core.pose import fit_pose
from statfit.synth.sample import camera_for_view
from statfit.renderer.images import render_target

from conftest import normal_map_scene

SIZE = 128


@pytest.fixture(scope="module")
def scene(embedded_model):
    shape = embedded_model.sample(np.random.default_rng(5), 1.0)
    camera = camera_for_view(shape, 20.0, 5.0, SIZE)
    return shape, camera


def test_camera_in_frame_sees_unit_points_where_the_camera_sees_world_points(scene, rng):
    shape, camera = scene
    frame = Frame.of(shape)
    pose = Similarity(1.3, Rotation.from_rotvec([0.1, -0.2, 0.05]).as_matrix(), np.array([0.2, -0.1, 0.3]))
    unit = frame.to_unit(shape)[::50]
    world = frame.from_unit(pose.apply(unit))
    expected, _ = camera.project(torch.as_tensor(world))
    got, depth = camera_in_frame(camera, frame, pose).project(torch.as_tensor(unit))
    np.testing.assert_allclose(got.numpy(), expected.numpy(), atol=1e-9)
    assert (depth > 0).all()


def test_world_normals_become_camera_normals(embedded_model, scene):
    shape, camera = scene
    normals, mask = render_target(shape, embedded_model.faces, camera)
    world = NormalMap(normals, mask)
    local = camera_space_normals(world, camera)
    # Independent expectation: the rasteriser's own camera-space normals of the same mesh.
    expected, covered = render_target(shape, embedded_model.faces, camera, space="camera")
    np.testing.assert_array_equal(covered, mask)
    np.testing.assert_allclose(local[mask], expected[mask], atol=1e-5)
    flipped = NormalMap((expected * [1, -1, -1]).astype(np.float32), mask)
    np.testing.assert_allclose(camera_space_normals(flipped, camera, "camera", "opengl")[mask], expected[mask],
                               atol=1e-6)
    # Surfaces seen by the camera face it: negative z in OpenCV camera axes.
    assert (local[mask][:, 2] < 0.2).mean() > 0.95


def _objective(model, shape, camera, dtype=torch.float64):
    normals, mask = render_target(shape, model.faces, camera)
    target = camera_space_normals(NormalMap(normals, mask), camera)
    return NormalMapObjective(torch.as_tensor(target, dtype=dtype), torch.as_tensor(mask), camera,
                              torch.as_tensor(model.faces, dtype=torch.long))


def test_objective_vanishes_at_the_target_and_grows_away_from_it(embedded_model, scene):
    shape, camera = scene
    objective = _objective(embedded_model, shape, camera)
    at_target = objective(torch.as_tensor(shape))
    # The antialiased outlines (against the background and where the nose hides the cheek) against the hard target.
    assert float(at_target["normal"]) < 0.02
    assert float(at_target["silhouette"]) < 0.02
    away = objective(torch.as_tensor(embedded_model.template))
    assert float(away["normal"]) > 10 * float(at_target["normal"]) + 0.01
    assert float(away["silhouette"]) > 2 * float(at_target["silhouette"])


def test_objective_gradient_matches_finite_differences(embedded_model, scene):
    shape, camera = scene
    objective = _objective(embedded_model, shape, camera)
    x = torch.as_tensor(embedded_model.template).clone().requires_grad_(True)
    total = sum(objective(x).values())
    total.backward()
    # A smooth displacement field: moves normals and the outline together.
    centred = embedded_model.template - embedded_model.template.mean(axis=0)
    direction = torch.as_tensor(np.sin(3.0 * centred / np.ptp(centred)) * [1.0, 0.5, -0.7])
    analytic = float((x.grad * direction).sum())
    # Small: the antialiased image jumps where an outline moves from one mesh edge to another, and
    # every occluding outline (the nose over the cheek) is one (at 1e-4 the normal term's difference
    # quotient is -2.6 against -3.38; at 3e-5 and 1e-5, -3.382 and -3.377).
    step = 1e-5 * float(np.ptp(centred))
    value = lambda t: float(sum(objective(x.detach() + t * direction).values()))  # noqa: E731
    numeric = (value(step) - value(-step)) / (2 * step)
    assert np.sign(analytic) == np.sign(numeric)
    assert analytic == pytest.approx(numeric, rel=0.05)


def _plate(centre: np.ndarray, size: float, tilt_deg: float, cells: int) -> tuple[np.ndarray, np.ndarray]:
    """A square plate facing -z (cells × cells quads), turned by ``tilt_deg`` about y: vertices, faces."""
    ticks = np.linspace(-size / 2, size / 2, cells + 1)
    grid = np.stack(np.meshgrid(ticks, ticks, indexing="xy"), axis=-1).reshape(-1, 2)
    vertices = Rotation.from_euler("y", tilt_deg, degrees=True).apply(np.c_[grid, np.zeros(len(grid))]) + centre
    corner = (np.arange(cells)[:, None] * (cells + 1) + np.arange(cells)[None]).reshape(-1)
    faces = np.concatenate([np.c_[corner, corner + 1, corner + cells + 2],
                            np.c_[corner, corner + cells + 2, corner + cells + 1]])
    return vertices, faces


def test_an_occluding_outline_inside_the_mask_gets_a_normal_gradient():
    # A tilted plate in front of a larger one that covers every pixel around it: moving the front
    # plate sideways changes no pixel's coverage (the silhouette term has nothing to say), only which
    # normals the pixels along its outline show. Plain rasterisation gives that no gradient; the
    # antialiased normal image must, matching finite differences and pointing towards the target.
    back, back_faces = _plate(np.array([0.0, 0.0, 3.0]), 2.0, 0.0, 4)
    front, front_faces = _plate(np.array([0.0, 0.0, 2.0]), 0.6, 35.0, 4)
    vertices = np.concatenate([back, front])
    faces = np.concatenate([back_faces, front_faces + len(back)])
    camera = Camera(64, 64, np.array([[64.0, 0, 32], [0, 64.0, 32], [0, 0, 1]]), np.eye(4))
    on_front = np.arange(len(vertices)) >= len(back)
    sideways = torch.as_tensor(np.where(on_front[:, None], [1.0, 0.0, 0.0], 0.0))
    target = vertices + 0.03 * sideways.numpy()                 # the front plate 1 pixel to the right
    normals, mask = render_target(target, faces, camera, space="camera")
    objective = NormalMapObjective(torch.as_tensor(normals, dtype=torch.float64), torch.as_tensor(mask), camera,
                                   torch.as_tensor(faces, dtype=torch.long))
    x = torch.as_tensor(vertices).clone().requires_grad_(True)
    terms = objective(x)
    terms["silhouette"].backward(retain_graph=True)
    assert float((x.grad * sideways).sum()) == pytest.approx(0.0, abs=1e-12)
    x.grad = None
    terms["normal"].backward()
    analytic = float((x.grad * sideways).sum())
    step = 1e-6
    value = lambda t: float(objective(x.detach() + t * sideways)["normal"])  # noqa: E731
    numeric = (value(step) - value(-step)) / (2 * step)
    assert analytic < -0.1                                       # moving right lowers the error (-0.55)
    assert analytic == pytest.approx(numeric, rel=0.02)


def test_pose_search_recovers_a_known_rigid_motion(embedded_model, scene):
    _, camera = scene
    template = embedded_model.template
    frame = Frame.of(template)
    truth = Similarity(1.0, Rotation.from_rotvec([0.0, np.radians(8.0), np.radians(-4.0)]).as_matrix(),
                       np.array([0.04, -0.03, 0.0]))
    unit_camera = camera_in_frame(camera, frame)
    moved = frame.from_unit(truth.apply(frame.to_unit(template)))
    objective = _objective(embedded_model, frame.to_unit(moved), unit_camera, torch.float32)
    found = fit_pose(torch.as_tensor(frame.to_unit(template), dtype=torch.float32), objective, iterations=300,
                     fixed_axis=unit_camera.rotation[2].float()).pose
    angle = np.degrees(Rotation.from_matrix(found.rotation @ truth.rotation.T).magnitude())
    assert angle < 1.0
    unit = frame.to_unit(template)
    assert np.abs(found.apply(unit) - truth.apply(unit)).max() < 0.03


def test_the_shape_coefficients_take_their_own_step_and_reach_a_shape_far_from_the_mean():
    """A squared distance to the mean moved by 3 units along one direction: the optimum is that
    coefficient at 3 / (1 + prior), in closed form. At the pose's step (0.01) 200 Adam steps move
    it ~2 at most; at its own step (0.05) it gets there."""
    rng = np.random.default_rng(0)
    vertices = torch.as_tensor(rng.normal(size=(50, 3)))
    direction = torch.as_tensor(rng.normal(size=(1, 50, 3)))
    direction /= direction.norm()
    target = vertices + 3.0 * direction[0]
    loss = lambda y: {"data": (y - target).square().sum()}  # noqa: E731
    optimum = 3.0 / (1.0 + 1e-3)                         # d/dc [(c − 3)² + 10⁻³ c²] = 0
    common = dict(iterations=200, lr=0.01, shape_basis=direction, shape_prior=1e-3, move=False)
    slow = fit_pose(vertices, loss, **common)
    fast = fit_pose(vertices, loss, shape_lr=0.05, **common)
    reached = lambda fit: float(((fit.shape - vertices) * direction[0]).sum())  # noqa: E731
    assert reached(slow) < 2.1
    assert reached(fast) == pytest.approx(optimum, abs=0.02)


def test_the_pose_search_stops_once_settled_and_not_before():
    """``settle``: the search stops at the first window of SETTLE_WINDOW iterations over which its
    best value fell by less than that share, and finds the same optimum (a translation, closed form:
    the mean offset) as the full run; without it every iteration runs."""
    from statfit.core.pose import SETTLE_WINDOW

    rng = np.random.default_rng(1)
    vertices = torch.as_tensor(rng.normal(size=(60, 3)))
    target = vertices + torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64) + 0.05 * torch.as_tensor(
        rng.normal(size=(60, 3)))
    calls = []

    def loss(y):
        calls.append(1)
        return {"data": (y - target).square().sum(dim=1).mean()}

    full = fit_pose(vertices, loss, iterations=600, lr=0.01)
    assert len(calls) == 600
    calls.clear()
    settled = fit_pose(vertices, loss, iterations=600, lr=0.01, settle=1e-3)
    assert SETTLE_WINDOW < len(calls) < 600 and len(calls) % SETTLE_WINDOW == 0
    optimum = (target - vertices).mean(dim=0).numpy()
    moved = lambda fit: fit.pose.apply(vertices.numpy()).mean(axis=0) - vertices.numpy().mean(axis=0)  # noqa: E731
    np.testing.assert_allclose(moved(full), optimum, atol=0.01)
    np.testing.assert_allclose(moved(settled), optimum, atol=0.01)
    assert settled.loss <= full.loss * (1 + 1e-2)


def test_rigid_alignment_recovers_a_moved_target(embedded_model, scene):
    shape, camera = scene
    turn = Rotation.from_rotvec([0.0, np.radians(10.0), 0.0]).as_matrix()
    centre = shape.mean(axis=0)
    moved = (shape - centre) @ turn.T + centre + [0.01, -0.01, 0.0]
    normals, mask = render_target(moved, embedded_model.faces, camera)
    errors = {}
    for align in ("none", "rigid"):
        fit = reconstruct(embedded_model, NormalMap(normals, mask), camera, "statistical", align=align,
                          iterations=150)
        errors[align] = float(np.linalg.norm(fit.vertices - moved, axis=1).mean())
    assert errors["rigid"] < 0.5 * errors["none"], errors
    assert np.degrees(Rotation.from_matrix(fit.transform.rotation @ turn.T).magnitude()) < 2.0


def test_rigid_alignment_leaves_a_target_in_place_in_place(embedded_model, scene):
    shape, camera = scene
    normals, mask = render_target(shape, embedded_model.faces, camera)
    fit = reconstruct(embedded_model, NormalMap(normals, mask), camera, "statistical", iterations=1)
    np.testing.assert_array_equal(fit.transform.rotation, np.eye(3))
    np.testing.assert_array_equal(fit.transform.translation, np.zeros(3))


def test_downsampled_map_matches_a_render_at_the_reduced_camera(embedded_model, scene):
    shape, _ = scene
    camera = camera_for_view(shape, 20.0, 5.0, 2 * SIZE)
    normals, mask = render_target(shape, embedded_model.faces, camera)
    target = torch.as_tensor(camera_space_normals(NormalMap(normals, mask), camera))
    coarse, coarse_mask, coarse_camera = downsampled(target, torch.as_tensor(mask), camera, SIZE)
    assert (coarse_camera.width, coarse_camera.height) == (SIZE, SIZE)
    expected_normals, expected_mask = render_target(shape, embedded_model.faces, coarse_camera)
    expected = camera_space_normals(NormalMap(expected_normals, expected_mask), coarse_camera)
    both = coarse_mask.numpy() & expected_mask
    assert (coarse_mask.numpy() == expected_mask).mean() > 0.995
    assert np.abs(coarse.numpy()[both] - expected[both]).mean() < 0.01


def test_similarity_alignment_takes_a_map_in_other_units(embedded_model):
    """A map and camera in millimetres, the model in metres: `rigid` refuses, `similarity` fits.
    From one view the scale is known only with the depth (scaling about the camera centre leaves
    the image unchanged), so the check is the image of the fit, and a scale near 1000."""
    shape = embedded_model.sample(np.random.default_rng(2), 1.0) * 1000.0
    camera = camera_for_view(shape, 20.0, 0.0, SIZE)
    normal_map = NormalMap(*render_target(shape, embedded_model.faces, camera))
    with pytest.raises(StatfitError, match="different units"):
        reconstruct(embedded_model, normal_map, camera, "statistical", iterations=1)
    fit = reconstruct(embedded_model, normal_map, camera, "statistical", align="similarity", iterations=100)
    assert 800 < fit.transform.scale < 1250
    _, covered = render_target(fit.vertices, embedded_model.faces, camera)
    assert (covered & normal_map.mask).sum() > 0.9 * (covered | normal_map.mask).sum()


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-5, 1e-3, 0.3, 2.0, 3.1])
def test_rodrigues_is_the_matrix_exponential_with_its_gradient(angle):
    """The pose's rotation (Rodrigues' formula, which a CUDA graph can capture) against torch's
    matrix exponential of the skew matrix: the same matrix and the same gradient, at ω = 0 too."""
    from statfit.core.pose import _skew, rotation_of

    omega = (angle * torch.nn.functional.normalize(torch.tensor([0.3, -1.0, 0.6], dtype=torch.float64), dim=0)
             ).requires_grad_()
    weights = torch.linspace(-1.0, 1.0, 9, dtype=torch.float64).view(3, 3)
    ours, reference = rotation_of(omega), torch.linalg.matrix_exp(_skew(omega))
    torch.testing.assert_close(ours, reference, rtol=0, atol=1e-14)
    gradient, = torch.autograd.grad((ours * weights).sum(), omega)
    expected, = torch.autograd.grad((reference * weights).sum(), omega)
    torch.testing.assert_close(gradient, expected, rtol=0, atol=1e-12)


def test_the_visibility_is_reused_where_no_graph_captures_the_fit_and_never_for_the_paper(monkeypatch):
    import statfit.render.visibility as visibility
    from statfit.render.visibility import visibility_every

    monkeypatch.setattr(visibility, "VISIBILITY_EVERY", 4)       # shipped: 4 (docs/studies.md §31)
    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert visibility_every("tuned", cpu) == 4
    assert visibility_every("paper", cpu) == 1
    monkeypatch.delenv("STATFIT_CUDA_GRAPHS", raising=False)
    assert visibility_every("tuned", cuda) == 1
    monkeypatch.setenv("STATFIT_CUDA_GRAPHS", "0")
    assert visibility_every("tuned", cuda) == 4


def test_the_alignment_refreshes_the_visibility_every_call_unless_told_to_reuse_it(monkeypatch):
    import statfit.render.visibility as visibility
    from statfit.render.visibility import alignment_visibility

    assert alignment_visibility(4, 1.0) == {"visibility_every": 1, "visibility_moved": None}   # shipped (§31)
    monkeypatch.setattr(visibility, "VISIBILITY_IN_ALIGNMENT", True)
    assert alignment_visibility(4, 1.0) == {"visibility_every": 4, "visibility_moved": 1.0}


def test_a_default_render_fit_reuses_the_visibility_in_its_stages_and_not_in_its_alignment(embedded_model):
    """Counted on a real fit: the alignment's renderer refreshes on every call, the fit's on one in
    ``VISIBILITY_EVERY`` (and at each stage's start)."""
    from statfit.render.job import reconstruct
    from statfit.render.visibility import VISIBILITY_EVERY
    from statfit.renderer.steady import SteadyRenderer

    normal_map, camera = normal_map_scene(embedded_model, 48)
    # keyed by the renderer itself, which the dict keeps alive: keyed by id(), a renderer made after
    # the alignment's was collected can take its id and the two counts merge
    counts: dict[SteadyRenderer, list[int]] = {}
    call, refresh = SteadyRenderer.__call__, SteadyRenderer._visibility

    def counted_call(self, *args, **kwargs):
        counts.setdefault(self, [0, 0])[0] += 1
        return call(self, *args, **kwargs)

    def counted_refresh(self, *args, **kwargs):
        counts.setdefault(self, [0, 0])[1] += 1
        return refresh(self, *args, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(SteadyRenderer, "__call__", counted_call)
        patch.setattr(SteadyRenderer, "_visibility", counted_refresh)
        # on the CPU: a fit a CUDA graph captures refreshes every call (the test above)
        reconstruct(embedded_model, normal_map, camera, "default", align="rigid", iterations=40, threads=1,
                    device="cpu")
    (alignment_calls, alignment_refreshes), (fit_calls, fit_refreshes) = counts.values()
    assert alignment_refreshes == alignment_calls > 0
    assert fit_calls / VISIBILITY_EVERY <= fit_refreshes < fit_calls / 2


def test_the_movement_limit_applies_only_where_the_visibility_is_reused(monkeypatch):
    import statfit.render.visibility as visibility
    from statfit.render.visibility import visibility_moved

    cpu = torch.device("cpu")
    monkeypatch.setattr(visibility, "VISIBILITY_MOVED", 1.0)
    monkeypatch.setattr(visibility, "VISIBILITY_EVERY", 1)
    assert visibility_moved("tuned", cpu) is None
    monkeypatch.setattr(visibility, "VISIBILITY_EVERY", 16)
    assert visibility_moved("tuned", cpu) == 1.0
    assert visibility_moved("paper", cpu) is None
