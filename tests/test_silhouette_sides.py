"""The one-sided silhouette terms: for models of part of what a normal map shows (a face mask in a
map of a whole head; issue 37, docs/studies.md §18), the rule that picks it, and for maps of part of
what the model makes (a face cut out of a photo, fitted with a head: the covering term, §24)."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
import trimesh

from conftest import run_cli
from statfit.geometry.metrics import facing_share, surface_distance
from statfit.model.cut import region_part
from statfit.objectives.normals import NormalMapObjective
from statfit.render.job import camera_space_normals, reconstruct, silhouette_sides
from statfit.renderer.images import render_target
from statfit.structures.normal_map import NormalMap
from statfit.synth.sample import camera_for_view


def test_facing_share_of_closed_half_and_flat_surfaces():
    sphere = trimesh.creation.icosphere(subdivisions=4)
    assert facing_share(sphere.vertices, sphere.faces) < 1e-12
    upper = sphere.faces[sphere.vertices[sphere.faces].mean(axis=1)[:, 2] > 0]
    # a hemisphere shell: its disc's area πr² over its own 2πr²
    assert facing_share(sphere.vertices, upper) == pytest.approx(0.5, abs=0.02)
    plane = trimesh.creation.box().vertices[[0, 1, 2, 3]]     # the x = -0.5 face: a flat square
    assert facing_share(plane, np.array([[0, 1, 3], [0, 3, 2]])) == pytest.approx(1.0)


@pytest.fixture(scope="module")
def face_mask(embedded_model):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")      # the landmarks outside the face are dropped
        return region_part(embedded_model, "face")


def test_auto_gives_a_mask_the_one_sided_term_and_a_head_the_two_sided(embedded_model, face_mask):
    assert silhouette_sides("auto", face_mask) == "one-sided"
    assert silhouette_sides("auto", embedded_model) == "two-sided"
    assert silhouette_sides("two-sided", face_mask) == "two-sided"


def _objective(model, person, faces, size, one_sided, covering=False):
    camera = camera_for_view(person, 20.0, 5.0, size)
    normal_map = NormalMap(*render_target(person, faces, camera))
    target = torch.as_tensor(camera_space_normals(normal_map, camera))
    return NormalMapObjective(target, torch.as_tensor(normal_map.mask), camera,
                              torch.as_tensor(model.faces, dtype=torch.long), one_sided=one_sided, covering=covering)


def test_one_sided_counts_only_coverage_outside_the_mask(embedded_model, face_mask):
    # The mask in place inside the head's outline: nothing outside, so the one-sided term is 0 (and
    # has no gradient) while the two-sided one asks the mask to cover the whole head.
    head = embedded_model.template
    inside = torch.as_tensor(face_mask.template)
    one, two = (_objective(face_mask, head, embedded_model.faces, 64, sided) for sided in (True, False))
    assert float(two(inside)["silhouette"]) > 0.05
    x = inside.clone().requires_grad_()
    one(x)["silhouette"].backward()
    assert float(one(inside)["silhouette"]) == 0.0 and float(x.grad.abs().max()) == 0.0
    # Blown up beyond the head's outline, the mask's excess counts on both sides alike (the part
    # inside the outline that the two-sided term adds is what tells them apart).
    centre = inside.mean(dim=0)
    big = centre + 3.0 * (inside - centre)
    assert float(one(big)["silhouette"]) > 0.5 * float(two(big)["silhouette"]) > 0


def test_a_mask_fitted_to_a_whole_heads_map_lands_closer_with_the_one_sided_term(embedded_model, face_mask):
    """Measured on ICT's mask (docs/studies.md §18): 13.2 → 6.5% and 10.0 → 5.9% of the radius. Here
    the embedded head's face cut out, a sampled head's 96² map, 120 default iterations (measured
    2026-11-26: 0.0137 → 0.0055)."""
    rng = np.random.default_rng(2)
    person = embedded_model.sample(rng, 1.0)
    camera = camera_for_view(person, 20.0, 5.0, 96)
    normal_map = NormalMap(*render_target(person, embedded_model.faces, camera))
    face = np.unique(embedded_model.faces[np.isin(embedded_model.faces, embedded_model.regions["face"]).all(axis=1)])
    errors = {}
    for sides in ("two-sided", "one-sided"):
        fit = reconstruct(face_mask, normal_map, camera, "default", silhouette=sides, iterations=120, threads=1)
        errors[sides] = float(surface_distance(person[face], fit.vertices, face_mask.faces).mean())
    assert errors["one-sided"] < 0.8 * errors["two-sided"], errors


def test_covering_counts_only_the_mask_the_model_leaves_uncovered(embedded_model, face_mask):
    # A head in place over a map of its face alone: it covers the mask (but for the antialiased edge
    # pixels where the face's outline is the head's), so the covering term is nearly 0 while the
    # two-sided one asks the head to shrink to the face's outline.
    head = torch.as_tensor(embedded_model.template)
    covering, two = (_objective(embedded_model, face_mask.template, face_mask.faces, 64, False, cover)
                     for cover in (True, False))
    assert float(two(head)["silhouette"]) > 0.05
    assert float(covering(head)["silhouette"]) < 0.02 * float(two(head)["silhouette"])
    # Shrunk inside the face's outline, the head leaves mask uncovered: that counts on both sides alike.
    centre = head.mean(dim=0)
    small = centre + 0.3 * (head - centre)
    assert float(covering(small)["silhouette"]) > 0.5 * float(two(small)["silhouette"]) > 0


def test_a_head_fitted_to_a_map_of_its_face_alone_lands_closer_with_the_covering_term(embedded_model):
    """Measured on ICT's head and the mask family's people (docs/studies.md §24). Here a sampled
    embedded head's face alone in a 96² map, the embedded head model, 120 default iterations, scored
    (measured 2026-11-27, mean vertex error: two-sided 0.0081, covering 0.0016)."""
    rng = np.random.default_rng(2)
    person = embedded_model.sample(rng, 1.0)
    face_faces = embedded_model.faces[np.isin(embedded_model.faces, embedded_model.regions["face"]).all(axis=1)]
    camera = camera_for_view(person, 20.0, 5.0, 96)
    normal_map = NormalMap(*render_target(person, face_faces, camera))
    errors = {}
    for sides in ("two-sided", "covering"):
        fit = reconstruct(embedded_model, normal_map, camera, "default", silhouette=sides, iterations=120, threads=1)
        errors[sides] = float(np.linalg.norm(fit.vertices - person, axis=1).mean())
    assert errors["covering"] < 0.8 * errors["two-sided"], errors


def test_an_unknown_silhouette_is_refused_in_one_line(tmp_path):
    exr, camera = tmp_path / "n.exr", tmp_path / "cam.json"
    assert run_cli(["synth", "normals", "--size", "32", "--out", str(exr), "--camera-out", str(camera)])[0] == 0
    code, err = run_cli(["render", str(exr), "--camera", str(camera), "--silhouette", "sideways", "--out",
                         str(tmp_path / "fit.ply")])
    assert code == 2 and err.count("\n") == 1 and "unknown silhouette" in err
    assert not (tmp_path / "fit.ply").exists()
    code, err = run_cli(["batch", "render", str(exr), "--camera", str(camera), "--silhouette", "sideways",
                         "--out-dir", str(tmp_path / "fits")])
    assert code == 2 and err.count("\n") == 1 and "unknown silhouette" in err
    assert not (tmp_path / "fits").exists()
