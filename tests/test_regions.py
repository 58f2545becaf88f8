"""--region on the normal-map job: the normal term sees only the region's pixels, and a fit with a
region ignores geometry outside it."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import trimesh

from statfit.render.job import camera_space_normals
from statfit.structures.normal_map import NormalMap
from statfit.model.statmodel import region_triangles
from statfit.objectives.normals import NormalMapObjective
from statfit.synth.sample import camera_for_view
from statfit.renderer.images import render_target
from test_cli import run
from test_cli_models import mean_error


@pytest.fixture(autouse=True)
def _threads():
    """One torch thread (overrides conftest's two), as in test_cli_models: these fits slow down 4×
    with two threads while the other core is busy."""
    torch.set_num_threads(1)


def test_region_normal_term_ignores_vertices_away_from_the_region(embedded_model):
    """Pushing in vertices two rings away from the face changes the whole-map normal term but not the
    face-region term (the face's pixels and vertex normals do not depend on them)."""
    shape = embedded_model.sample(np.random.default_rng(5), 1.0)
    camera = camera_for_view(shape, 20.0, 5.0, 128)
    normals, mask = render_target(shape, embedded_model.faces, camera)
    target = torch.as_tensor(camera_space_normals(NormalMap(normals, mask), camera))
    faces = torch.as_tensor(embedded_model.faces, dtype=torch.long)
    region = torch.as_tensor(region_triangles(embedded_model, "face"))
    near = np.zeros(embedded_model.num_vertices, dtype=bool)
    near[embedded_model.regions["face"]] = True
    for _ in range(2):  # grow by two rings of triangles
        near[embedded_model.faces[near[embedded_model.faces].any(axis=1)].reshape(-1)] = True
    moved = shape.copy()
    vertex_normals = trimesh.Trimesh(shape, embedded_model.faces, process=False).vertex_normals
    moved[~near] -= 0.01 * vertex_normals[~near]
    whole = NormalMapObjective(target, torch.as_tensor(mask), camera, faces)
    face_only = NormalMapObjective(target, torch.as_tensor(mask), camera, faces, region_faces=region)
    at, away = (torch.as_tensor(v) for v in (shape, moved))
    assert float(whole(away)["normal"]) > float(whole(at)["normal"]) + 0.01
    assert float(face_only(away)["normal"]) == pytest.approx(float(face_only(at)["normal"]), abs=1e-9)


def test_render_with_a_region_ignores_a_cap(tmp_path, capsys, embedded_model):
    """A 2 cm 'cap' added to every vertex off the face: the face-region fit's face is closer to the
    truth than the whole-map fit's."""
    face = np.zeros(embedded_model.num_vertices, dtype=bool)
    face[embedded_model.regions["face"]] = True
    normals = trimesh.Trimesh(embedded_model.template, embedded_model.faces, process=False).vertex_normals
    np.savez(tmp_path / "cap.npz", names=np.array(["cap"]), deltas=np.where(face[:, None], 0.0, 0.02 * normals)[..., None])
    files = {name: str(tmp_path / name) for name in ("n.exr", "camera.json", "gt.ply")}
    assert run(["synth", "normals", "--seed", "3", "--yaw", "20", "--size", "128", "--out", files["n.exr"],
                "--camera-out", files["camera.json"], "--gt", files["gt.ply"], "--delta", str(tmp_path / "cap.npz"),
                "--delta-name", "cap"], capsys)[0] == 0
    for name, extra in (("whole", []), ("face", ["--region", "face"])):
        code, out, _ = run(["render", files["n.exr"], "--camera", files["camera.json"], "--align", "none",
                            "--iterations", "40", "-q", "--json", "-o", str(tmp_path / f"{name}.ply"), *extra], capsys)
        assert code == 0
    assert "silhouette" not in json.loads(out)["final_loss"]
    whole, region = (mean_error(tmp_path / f"{n}.ply", tmp_path / "gt.ply", face) for n in ("whole", "face"))
    assert region < 0.8 * whole
