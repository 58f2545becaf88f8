"""Real scans: the simulated range scanner, mesh scans sampled by area, normals, clutter left out
of the data term, the automatic pose search, and the scans it must refuse."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import trimesh

import statfit.core.threads as threads_module
from statfit.geometry.closest import ClosestPointQuery, open_edges
from statfit.errors import StatfitError
from statfit.registration.pose.search import estimate_pose
from statfit.io.landmarks import read_landmarks
from statfit.io.mesh import read_mesh
from statfit.objectives.scan import ScanObjective
from statfit.geometry.metrics import surface_distance
from statfit.registration.job import register
from statfit.structures.scan import Scan, estimate_normals
from statfit.synth.scanner import neck_tube, realistic_scan
from statfit.synth.sample import scan_from_view

from conftest import run_cli


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1))))


def _ict_with_inner_landmarks(ict_model):
    from statfit.model.statmodel import with_landmarks
    from conftest import ICT_DIR

    return with_landmarks(ict_model, np.load(ICT_DIR / "ict_face_identity.npz")["landmarks68"][17:68])


def _ict_person(model, seed: int, units: str = "mm", posed: bool = True, clutter: float = 0.5,
                scanner: np.random.Generator | None = None):
    """A realistic scan of someone outside ``model``'s span, as the real-scans benchmark makes them
    (docs/benchmarks.md §8): an identity sample plus an expression the model lacks, with hair,
    neck and shoulders worth ``clutter`` of the face's points, from a yaw in ±45°; ``scanner``: the
    scanner's own draws (default: the person's generator goes on)."""
    from statfit.synth.sample import load_delta
    from conftest import ICT_DIR

    expressions = ICT_DIR / "ict_face_expressions.npz"
    with np.load(expressions) as data:
        names = [str(name) for name in data["names"]]
    rng = np.random.default_rng(1000 + seed)
    expression = names[rng.integers(len(names))]
    shape = model.sample(rng) + rng.uniform(0.5, 1.0) * load_delta(str(expressions), expression)
    yaw = rng.uniform(-45, 45)
    return realistic_scan(shape, model.faces, rng if scanner is None else scanner, yaw_deg=yaw, clutter=clutter,
                          units=units, posed=posed)


def test_realistic_scan_holds_the_shape_clutter_as_asked_and_its_pose(embedded_model):
    model = embedded_model
    shape = model.sample(np.random.default_rng(0))
    scan = realistic_scan(shape, model.faces, np.random.default_rng(1), clutter=0.5, units="mm", noise=0.0)
    assert scan.clutter_ratio == pytest.approx(0.5, abs=0.05)
    assert np.allclose(scan.truth, scan.transform.apply(shape))
    assert scan.transform.scale == pytest.approx(1000.0)           # the model is in metres, the scan in mm
    assert np.allclose(scan.transform.rotation @ scan.transform.rotation.T, np.eye(3), atol=1e-12)
    on_distance = surface_distance(scan.vertices[scan.on_shape], scan.truth, model.faces)
    off_distance = surface_distance(scan.vertices[~scan.on_shape], scan.truth, model.faces)
    assert on_distance.max() < 1e-6 * scan.transform.scale         # noise-free: the shape's points lie on it
    assert np.median(off_distance) > 5.0                           # clutter lies off it (mm)
    # the scan is a mesh of the grid's hits, wound towards the viewer
    assert len(scan.faces) > len(scan.vertices)
    clean = realistic_scan(shape, model.faces, np.random.default_rng(1), clutter=0.0, posed=False, units="m")
    assert clean.on_shape.all() and np.allclose(clean.truth, shape)


def test_realistic_scan_holds_only_the_clutter_parts_asked_for(embedded_model):
    model = embedded_model
    shape = model.sample(np.random.default_rng(0))
    up = lambda made: made.transform.inverse_apply(made.vertices)[:, 1]  # noqa: E731  (model frame, +y up)
    top, bottom = shape[:, 1].max(), shape[:, 1].min()
    hair = realistic_scan(shape, model.faces, np.random.default_rng(1), clutter=0.5, clutter_parts=("hair",))
    neck = realistic_scan(shape, model.faces, np.random.default_rng(1), clutter=0.5, clutter_parts=("neck",))
    # hair lies over the scalp: above the lowest point of the head; the neck tube below the head
    assert (~hair.on_shape).sum() > 50 and up(hair)[~hair.on_shape].min() > bottom
    assert neck.clutter_ratio > 0.3 and up(neck)[~neck.on_shape].max() < top
    assert up(hair)[~hair.on_shape].max() > top                   # the hair rises over the crown
    with pytest.raises(StatfitError, match="unknown clutter part"):
        realistic_scan(shape, model.faces, np.random.default_rng(1), clutter_parts=("hat",))


def test_synth_scan_clutter_parts_on_the_command_line(tmp_path):
    out = tmp_path / "scan.ply"
    assert run_cli(["synth", "scan", "--realistic", "--clutter-parts", "hair", "--out", str(out)])[0] == 0
    assert read_mesh(out)[0].shape[0] > 100
    code, err = run_cli(["synth", "scan", "--realistic", "--clutter-parts", "hair,hat", "--out", str(tmp_path / "x.ply")])
    assert code == 2 and err.count("\n") == 1 and "unknown --clutter-parts hat" in err
    code, err = run_cli(["synth", "scan", "--realistic", "--clutter-parts", " , ", "--out", str(tmp_path / "x.ply")])
    assert code == 2 and err.count("\n") == 1 and "needs at least one of hair, neck" in err
    assert not (tmp_path / "x.ply").exists()


def test_synth_scan_realistic_writes_a_mesh_its_truth_and_landmarks(tmp_path):
    scan, gt, marks = tmp_path / "scan.ply", tmp_path / "gt.ply", tmp_path / "marks.txt"
    code, err = run_cli(["synth", "scan", "--realistic", "--seed", "4", "--units", "cm", "--out", str(scan), "--gt",
                         str(gt), "--landmarks-out", str(marks)])
    assert code == 0, err
    vertices, faces = read_mesh(scan)
    truth, _ = read_mesh(gt)
    from statfit.model.statmodel import default_model_path, load_model
    model = load_model(default_model_path())
    assert np.allclose(read_landmarks(marks), truth[model.landmarks])
    assert np.ptp(truth, axis=0).max() == pytest.approx(100 * np.ptp(model.template, axis=0).max(), rel=0.3)
    code, err = run_cli(["synth", "scan", "--realistic", "--outliers", "0.1", "--out", str(tmp_path / "x.ply")])
    assert code == 2 and "--clutter" in err and not (tmp_path / "x.ply").exists()


@pytest.mark.parametrize("unit", [1.0, 10.0, 1000.0, 0.1 / 2.54, 1 / 2.54, 100 / 2.54])
def test_landmarks_give_the_unit_inches_too(unit):
    """A landmark similarity's scale (a person's size within ±10%, and more) gives the unit: a power
    of ten, or one over 2.54 (inches)."""
    from statfit.registration.pose.frames import landmark_units

    for size in (0.8, 0.9, 1.0, 1.1, 1.25):
        assert landmark_units(unit * size) == pytest.approx(unit, rel=1e-12), (unit, size)


def test_a_scan_in_inches_fits_as_the_same_scan_in_millimetres(tmp_path):
    """Scanner software exports inches too: the same person's realistic scan in mm and in inches,
    registered with landmarks, fits the same surface (the inch fit × 25.4 on the mm fit), and the
    summary names the units found. (Without landmarks the size cannot tell an inch scan from a
    partial metric one: docs/studies.md §39.)"""
    fits, factors = {}, {}
    for units in ("mm", "in"):
        scan, marks = tmp_path / f"scan_{units}.ply", tmp_path / f"marks_{units}.txt"
        code, err = run_cli(["synth", "scan", "--realistic", "--seed", "7", "--units", units, "--out", str(scan),
                             "--landmarks-out", str(marks)])
        assert code == 0, err
        out, log = tmp_path / f"fit_{units}.ply", tmp_path / f"fit_{units}.jsonl"
        code, err = run_cli(["register", str(scan), "--out", str(out), "--log", str(log), "-q",
                             "--landmarks", str(marks)])
        assert code == 0, err
        fits[units] = read_mesh(out)[0] * (25.4 if units == "in" else 1.0)
        factors[units] = json.loads(log.read_text().splitlines()[-1])["pose"]["units_factor"]
    assert factors["in"] == pytest.approx(factors["mm"] / 25.4, rel=1e-12), factors
    radius = np.sqrt(((fits["mm"] - fits["mm"].mean(axis=0)) ** 2).sum(axis=1).mean())
    assert np.linalg.norm(fits["in"] - fits["mm"], axis=1).mean() < 0.01 * radius


def test_mesh_scans_are_sampled_by_area_not_by_vertex_density():
    # a unit square in z = 0: the left half cut into 32×32 cells, the right half into one cell
    def grid(x0: float, cells: int) -> trimesh.Trimesh:
        u, v = np.meshgrid(np.linspace(x0, x0 + 0.5, cells + 1), np.linspace(0, 1, cells + 1), indexing="ij")
        i, j = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
        a = (i * (cells + 1) + j).ravel()
        faces = np.concatenate([np.stack([a, a + cells + 1, a + 1], 1), np.stack([a + 1, a + cells + 1, a + cells + 2], 1)])
        return trimesh.Trimesh(np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], 1), faces, process=False)

    mesh = trimesh.util.concatenate([grid(0.0, 32), grid(0.5, 1)])
    scan = Scan.from_mesh(mesh.vertices, mesh.faces, seed=0, count=20_000)
    share_left = float((scan.points[:, 0] < 0.5).mean())
    assert share_left == pytest.approx(0.5, abs=0.02)           # by vertices it would be > 0.99
    assert np.allclose(np.abs(scan.normals[:, 2]), 1.0)
    with pytest.raises(StatfitError, match="positive area"):
        Scan.from_mesh(np.zeros((3, 3)), np.array([[0, 1, 2]]))


def test_point_cloud_normals_are_the_surface_normals(rng):
    direction = rng.normal(size=(3000, 3))
    points = direction / np.linalg.norm(direction, axis=1, keepdims=True)   # a unit sphere
    normals = estimate_normals(points)
    assert np.abs((normals * points).sum(axis=1)).min() > 0.95
    assert (Scan.from_points(points).normals * points).sum(axis=1).min() > 0.95   # oriented outwards


def test_open_edges_of_a_closed_and_an_open_mesh():
    closed = torch.as_tensor(trimesh.creation.icosphere(1).faces)
    assert not open_edges(closed).any()
    single = torch.tensor([[0, 1, 2]])
    assert open_edges(single).all()


def test_points_off_the_template_leave_the_data_term():
    # template: the square [0, 1]² at z = 0; the scan: points on it, beyond its border, far above
    # it and on it with a perpendicular normal
    plane = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.]]),
                                                              np.array([[0, 1, 2], [0, 2, 3]]), 0.1))
    on = np.array([[0.3, 0.4, 0.001], [0.6, 0.5, -0.001], [0.5, 0.2, 0.0]])
    beyond = np.array([[1.2, 0.5, 0.0]])
    far = np.array([[0.5, 0.5, 0.5]])
    sideways = np.array([[0.4, 0.6, 0.0]])
    points = torch.as_tensor(np.concatenate([on, beyond, far, sideways]))
    normals = torch.tensor([[0, 0, 1.0]] * 3 + [[0, 0, -1.0]] * 2 + [[1.0, 0, 0]], dtype=torch.float64)
    query = ClosestPointQuery(plane.faces, len(plane.vertices))
    objective = ScanObjective(points, query, trim=0.0, normals=normals, clutter=True)
    objective.refresh(torch.as_tensor(plane.vertices))
    assert objective._keep.tolist() == [True, True, True, False, False, False]
    clean = ScanObjective(points, query, trim=0.0, normals=normals)      # a clean scan: the border rule only
    clean.refresh(torch.as_tensor(plane.vertices))
    assert clean._keep.tolist() == [True, True, True, False, True, True]


@pytest.mark.parametrize("seed,units", [(0, "mm"), (1, "cm"), (2, "m"), (3, "mm")])
def test_pose_units_and_offset_are_found_without_landmarks(embedded_model, seed, units):
    model = embedded_model
    rng = np.random.default_rng(seed)
    shape = model.sample(rng)
    made = realistic_scan(shape, model.faces, rng, yaw_deg=rng.uniform(-40, 40), clutter=0.5, units=units)
    estimate = estimate_pose(model, Scan.from_mesh(made.vertices, made.faces))
    assert _angle(estimate.transform.rotation, made.transform.rotation) < 3.0
    assert estimate.transform.scale == made.transform.scale         # the units, exactly: size is the modes'


def test_the_pose_searchs_candidates_on_threads_find_what_one_thread_finds(embedded_model, monkeypatch):
    """The refined candidates run on threads of their own where there are cores: every number of
    the estimate the same to the bit as one after another (a cluttered scan: all of step 5 runs)."""
    import statfit.registration.pose.search as search

    rng = np.random.default_rng(5)
    made = realistic_scan(embedded_model.sample(rng), embedded_model.faces, rng, yaw_deg=25.0, clutter=0.5)
    scan = Scan.from_mesh(made.vertices, made.faces)
    estimates = []
    for threads in (1, 3):
        monkeypatch.setattr(search, "task_threads", lambda tasks, cap, threads=threads: threads)
        estimates.append(estimate_pose(embedded_model, scan))
    alone, threaded = estimates
    for field in ("rotation", "translation"):
        assert np.array_equal(getattr(alone.transform, field), getattr(threaded.transform, field))
    assert alone.transform.scale == threaded.transform.scale
    assert np.array_equal(alone.coefficients, threaded.coefficients)
    assert (alone.score, alone.matched, alone.runner_up) == (threaded.score, threaded.matched, threaded.runner_up)


def test_threads_asked_for_cap_the_pose_searchs_own(embedded_model, monkeypatch):
    """`--threads 1` means one thread: the pose search's candidates then run one after another."""
    import statfit.registration.pose.search as search

    monkeypatch.setattr(threads_module, "available_cores", lambda: 4)
    pools = []
    monkeypatch.setattr(search, "map_in_threads", lambda work, items, threads: pools.append(threads) or
                        [work(item) for item in items])
    rng = np.random.default_rng(6)
    points = scan_from_view(embedded_model.sample(rng), embedded_model.faces, rng, 1500, 20.0)
    for threads in (1, None):
        register(embedded_model, points, "pca", iterations=2, threads=threads, fallback=False)
    assert pools == [1, 3]


def test_the_points_beyond_the_face_fits_scalp_are_the_hair(embedded_model):
    """On the true shape and pose, what the polish leaves out as hair is the hair: every point the
    scanner took off the hair layer (0.056–0.104 radii out) and none of the head's."""
    from statfit.structures.frame import Frame
    from statfit.registration.pose.search import POSE_FACE_RADIUS
    from statfit.registration.hair import hair_suspects
    from statfit.model.statmodel import face_triangles

    model = embedded_model
    rng = np.random.default_rng(3)
    shape = model.sample(rng)
    made = realistic_scan(shape, model.faces, rng, clutter=0.5, units="m", posed=False, noise=0.0,
                          clutter_parts=("hair",))
    frame = Frame.of(model.template)
    to_unit = lambda p: torch.as_tensor((p - frame.center) / frame.scale)  # noqa: E731  (scan and model frames coincide here)
    hair = hair_suspects(ClosestPointQuery(model.faces, model.num_vertices, k=2), to_unit(shape),
                         to_unit(made.vertices), torch.as_tensor(face_triangles(model, POSE_FACE_RADIUS))).numpy()
    assert (~made.on_shape).sum() > 100
    assert hair[~made.on_shape].mean() > 0.95 and not hair[made.on_shape].any()


def test_the_scalp_lies_above_and_behind_the_face(ict_model, embedded_model):
    """The scalp region holds the crown and the back of the head, and no triangle of the face
    (ICT: its inner landmarks' triangles) nor of the neck below it; a model with neither a face
    region nor landmarks has none."""
    import dataclasses

    from statfit.model.statmodel import scalp_triangles

    model = _ict_with_inner_landmarks(ict_model)
    scalp = scalp_triangles(model)
    template, faces = model.template, model.faces
    touching = lambda vertex: (faces == vertex).any(axis=1)  # noqa: E731
    crown = int(np.argmax(template[:, 1]))
    head = template[:, 1] > template[model.landmarks, 1].max()
    back = int(np.flatnonzero(head)[np.argmin(template[head, 2])])
    assert scalp[touching(crown)].all() and scalp[touching(back)].all()
    assert not scalp[np.isin(faces, model.landmarks).any(axis=1)].any()
    assert not scalp[touching(int(np.argmin(template[:, 1])))].any()
    bare = dataclasses.replace(embedded_model, regions={}, landmarks=None)
    assert scalp_triangles(bare) is None


def test_hair_is_what_lies_beyond_the_offset_off_the_face():
    """On a unit sphere, points pushed out along the normal by 0.08 (beyond HAIR_OFFSET 0.05) off the
    face are hair; 0.02 out, pushed in, or over the face (z > 0.5) are not."""
    from statfit.registration.hair import HAIR_OFFSET, hair_suspects

    sphere = trimesh.creation.icosphere(4)
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(400, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    offsets = rng.choice([-0.08, 0.02, 0.08], size=400)
    face = sphere.triangles_center[:, 2] > 0.5
    hair = hair_suspects(ClosestPointQuery(sphere.faces, len(sphere.vertices), k=3),
                         torch.as_tensor(sphere.vertices), torch.as_tensor(directions * (1 + offsets[:, None])),
                         torch.as_tensor(face)).numpy()
    off_face = directions[:, 2] < 0.45             # clear of the face's ragged border
    on_face = directions[:, 2] > 0.55
    assert 0.02 < HAIR_OFFSET < 0.08             # the offsets straddle it
    np.testing.assert_array_equal(hair[off_face], offsets[off_face] > HAIR_OFFSET)
    assert not hair[on_face].any()


def test_the_fit_leaves_the_hair_out_and_fits_the_rest_of_the_head(embedded_model):
    """With the clutter rules on, the fit drops the points beyond a face-only fit's scalp and those on
    the scalp region, and fits the rest of the head: the whole head lands nearer the truth than when
    the data term keeps to the face (the fallback when most of the scan lies out there), and the face
    as near as on the clean scan."""
    import importlib

    hair_module = importlib.import_module("statfit.registration.hair")
    model = embedded_model
    face = model.regions["face"]
    errors = {}
    for name, clutter, share in (("clean", 0.0, hair_module.MAX_HAIR_SHARE),
                                 ("hair left out", 0.5, hair_module.MAX_HAIR_SHARE), ("face only", 0.5, -1.0)):
        rng = np.random.default_rng(7)
        shape = model.sample(rng)
        made = realistic_scan(shape, model.faces, rng, clutter=clutter, holes=0, posed=False, units="m")
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(hair_module, "MAX_HAIR_SHARE", share)
            fit = register(model, Scan.from_mesh(made.vertices, made.faces), "pca", align="none", clutter=True)
        distance = np.linalg.norm(fit.vertices - shape, axis=1)
        errors[name] = (float(distance.mean()), float(distance[face].mean()))
    assert errors["hair left out"][0] < 0.5 * errors["face only"][0], errors    # measured 0.40
    assert errors["hair left out"][1] <= 1.1 * errors["clean"][1] + 1e-5, errors   # measured 0.64


def test_hair_does_not_tilt_the_pose(embedded_model):
    """Scans whose only clutter is hair: posed as well as with the hair cut out of the scan, and
    better than when the last polish fits the hair too (measured: 0.14–0.24° against 0.14–0.51°)."""
    import statfit.registration.hair as hair_module

    model = embedded_model
    angles = {"hair left out": [], "hair fitted": [], "hair cut out": []}
    for seed in range(3):
        rng = np.random.default_rng(seed)
        made = realistic_scan(model.sample(rng), model.faces, rng, yaw_deg=rng.uniform(-40, 40), clutter=0.5,
                              units="mm", clutter_parts=("hair",))
        shape_only = made.faces[made.on_shape[made.faces].all(axis=1)]
        for name, faces, share in (("hair left out", made.faces, hair_module.MAX_HAIR_SHARE),
                                   ("hair fitted", made.faces, -1.0), ("hair cut out", shape_only, 0.6)):
            with pytest.MonkeyPatch.context() as patch:
                patch.setattr(hair_module, "MAX_HAIR_SHARE", share)
                estimate = estimate_pose(model, Scan.from_mesh(made.vertices, faces))
            angles[name].append(_angle(estimate.transform.rotation, made.transform.rotation))
    mean = {name: float(np.mean(values)) for name, values in angles.items()}
    assert max(angles["hair left out"]) < 0.5, angles
    assert mean["hair left out"] < 0.6 * mean["hair fitted"], angles
    assert mean["hair left out"] < mean["hair cut out"] + 0.1, angles


def test_on_a_cluttered_scan_the_pose_leaves_the_scalp_to_the_hair(ict_model):
    """ICT people outside the model (an identity sample plus an expression it lacks) with hair,
    neck and shoulders: with the scalp region left out of the polish, the pose lands nearer the
    truth than when only the points beyond a face fit's scalp are (docs/studies.md §16, "The scalp
    as a region"; measured 0.34° against 0.88° on these four, 0.39° against 2.00° at worst; with
    the oldest numpy and scipy pyproject allows, 0.49° against 0.96°, 1.06° at worst: the search
    lands in another of its nearby minima when the linear algebra rounds otherwise)."""
    import statfit.registration.pose.search as global_align

    model = _ict_with_inner_landmarks(ict_model)
    angles: dict[str, list[float]] = {"scalp left out": [], "beyond the face fit only": []}
    for seed in range(4):
        made = _ict_person(model, seed)
        scan = Scan.from_mesh(made.vertices, made.faces)
        for name in angles:
            with pytest.MonkeyPatch.context() as patch:
                if name != "scalp left out":
                    patch.setattr(global_align, "scalp_triangles", lambda model: None)
                estimate = estimate_pose(model, scan)
            angles[name].append(_angle(estimate.transform.rotation, made.transform.rotation))
    left_out, beyond = (float(np.mean(values)) for values in angles.values())
    assert left_out < 0.6 * beyond, angles
    assert max(angles["scalp left out"]) < 1.25, angles


def test_a_scan_already_on_the_model_is_left_where_it_is(embedded_model):
    model = embedded_model
    rng = np.random.default_rng(5)
    points = scan_from_view(model.sample(rng), model.faces, rng, 3000, 30.0)
    estimate = estimate_pose(model, Scan.from_points(points))
    assert estimate.transform.scale == 1.0
    assert np.array_equal(estimate.transform.rotation, np.eye(3))
    assert np.allclose(estimate.transform.translation, 0.0, atol=1e-12)


@pytest.mark.parametrize("kind", ["sphere", "plane", "tube"])
def test_scans_of_something_else_are_refused(embedded_model, kind):
    model = embedded_model
    radius = float(np.ptp(model.template, axis=0).max() / 2)
    if kind == "sphere":
        mesh = trimesh.creation.icosphere(4, radius=radius)
    elif kind == "plane":
        box = trimesh.creation.box([2 * radius, 2 * radius, 1e-3 * radius])
        mesh = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(box.vertices, box.faces, radius / 20))
    else:
        mesh = neck_tube(model.template)
    with pytest.raises(StatfitError, match="does not look like the model"):
        estimate_pose(model, Scan.from_mesh(mesh.vertices, mesh.faces))


def test_register_cli_fits_a_posed_cluttered_mesh_scan_and_reports_the_pose(tmp_path):
    scan, gt, fit, log = tmp_path / "scan.ply", tmp_path / "gt.ply", tmp_path / "fit.ply", tmp_path / "fit.jsonl"
    assert run_cli(["synth", "scan", "--realistic", "--seed", "6", "--out", str(scan), "--gt", str(gt)])[0] == 0
    code, err = run_cli(["register", str(scan), "--method", "pca", "--out", str(fit), "--log", str(log), "--quiet"])
    assert code == 0, err
    summary = json.loads(log.read_text().splitlines()[-1])
    pose = summary["pose"]
    assert pose["units_factor"] == 1000.0 and pose["clutter_rules"] and not pose["face_only"]
    assert 0.05 < pose["hair_share"] < 0.6          # the hair left out, the rest of the head fitted
    fitted, _ = read_mesh(fit)
    truth, _ = read_mesh(gt)
    from statfit.geometry.align import umeyama
    from statfit.model.statmodel import default_model_path, load_model
    model = load_model(default_model_path())
    face = model.regions["face"]
    # the mean shape placed on the true face by the best similarity: what no pose search can beat
    placed_mean = umeyama(model.template[face], truth[face], with_scale=True).apply(model.template)
    error = np.linalg.norm(fitted - truth, axis=1)[face].mean()
    assert error < 0.8 * np.linalg.norm(placed_mean - truth, axis=1)[face].mean()   # measured 0.36 (0.75 on the face alone)


def test_register_refuses_a_sphere_with_one_line(tmp_path):
    sphere, out = tmp_path / "sphere.ply", tmp_path / "fit.ply"
    mesh = trimesh.creation.icosphere(4, radius=120.0)     # a head-sized ball in mm, somewhere
    mesh.apply_translation([300.0, -40.0, 900.0])
    sphere.write_bytes(mesh.export(file_type="ply"))
    code, err = run_cli(["register", str(sphere), "--out", str(out)])
    assert code == 2 and "does not look like the model" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_clutter_does_not_move_a_fit_in_the_models_frame(embedded_model):
    model = embedded_model
    errors = []
    for clutter in (0.0, 0.5):
        rng = np.random.default_rng(7)
        shape = model.sample(rng)
        made = realistic_scan(shape, model.faces, rng, clutter=clutter, holes=0, posed=False, units="m")
        fit = register(model, Scan.from_mesh(made.vertices, made.faces), "pca", align="none", clutter=True)
        errors.append(np.linalg.norm(fit.vertices - shape, axis=1)[model.regions["face"]].mean())
    assert errors[1] <= 1.1 * errors[0] + 1e-5


@pytest.fixture(scope="module")
def ict_people(ict_model) -> list[dict]:
    """Six people past the real-scans benchmark's 50 (seeds 50–55), in mm, cm and m, each scanned
    twice with the same scanner draws: with hair, neck and shoulders worth 50% of its points, and
    without clutter. The cluttered scan is fitted with `pca` posed without landmarks ("found") and
    posed by its 51 landmarks (1 mm noise, weight 0: the two fits differ by the pose alone:
    "placed"); the clean scan posed without landmarks ("clean"). Errors in mm."""
    model = _ict_with_inner_landmarks(ict_model)
    template = model.template
    near = np.linalg.norm(template[:, None] - template[model.landmarks][None], axis=-1).min(axis=1) < 3.0
    people = []
    for seed, units in zip(range(50, 56), ("mm", "cm", "m") * 2):
        to_mm = {"mm": 1.0, "cm": 10.0, "m": 1000.0}[units]
        made = {clutter: _ict_person(model, seed, units, clutter=clutter, scanner=np.random.default_rng(seed))
                for clutter in (0.5, 0.0)}
        scans = {clutter: Scan.from_mesh(each.vertices, each.faces) for clutter, each in made.items()}
        landmarks = made[0.5].truth[model.landmarks]
        noise = np.random.default_rng(seed).normal(scale=1.0 / to_mm, size=landmarks.shape)
        fits = {"found": register(model, scans[0.5], "pca", threads=1),
                "placed": register(model, scans[0.5], "pca", landmarks=landmarks + noise, landmark_weight=0.0,
                                   threads=1),
                "clean": register(model, scans[0.0], "pca", threads=1)}
        error = lambda fit, truth: to_mm * np.linalg.norm(fit.vertices - truth, axis=1)  # noqa: E731
        people.append({
            "landmarks": {name: float(error(fits[name], made[0.5].truth)[model.landmarks].mean())
                          for name in ("found", "placed")},
            "face": {"found": float(error(fits["found"], made[0.5].truth)[near].mean()),
                     "clean": float(error(fits["clean"], made[0.0].truth)[near].mean())},
            "angle": _angle(fits["found"].transform.rotation, made[0.5].transform.rotation)})
    return people


@pytest.mark.slow
def test_the_pose_found_places_the_fit_as_well_as_landmarks_do(ict_people):
    """Issue 11's pose target at a looser margin, on six people past the benchmark's 50, in mm, cm
    and m: the `pca` fit posed without landmarks against the same fit posed by its landmarks.
    Landmark error within 1.5× on ≥ 5 of 6 (the benchmark, docs/benchmarks.md §8: within 1.25× on 48
    of 50), and never turned away."""
    ratios = [person["landmarks"]["found"] / person["landmarks"]["placed"] for person in ict_people]
    assert sum(ratio <= 1.5 for ratio in ratios) >= 5, ratios
    assert max(person["angle"] for person in ict_people) < 10, ict_people


@pytest.mark.slow
def test_clutter_hardly_moves_the_face_of_a_scan_fitted_as_it_comes(ict_people):
    """Issue 11's clutter target at a looser margin, on the six people past the benchmark's: each
    scanned without clutter and with hair, neck and shoulders worth 50% of its points (the same
    scanner draws otherwise), posed without landmarks and fitted with `pca`. The mean face error
    (vertices within 3 cm of an inner landmark) changes by at most 20% (measured 1.08 → 1.14 mm, +5%;
    before the scalp region, 1.08 → 1.72 mm, +59%; the benchmark, docs/benchmarks.md §8, asks 10% of the
    default)."""
    clean = float(np.mean([person["face"]["clean"] for person in ict_people]))
    cluttered = float(np.mean([person["face"]["found"] for person in ict_people]))
    assert cluttered <= 1.2 * clean, ict_people
