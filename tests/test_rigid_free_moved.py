"""`render` drops the modes' rigid motion where its alignment moved the model off the place they give
its people (statfit.model.cut.rigid_motion_distance, statfit.render.job.posed_view): the distance
against its closed form, the rule's choice, and the fit it gives."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from statfit.model.cut import OFF_ITS_PLACE, fitting_model_and_rule, rigid_motion_distance, without_rigid_motion
from statfit.model.statmodel import model_from_arrays
from test_rigid_free import moving_head, rigid_fields


def rigid_model(embedded_model, shift_std: float, turn_std: float):
    """The embedded head with two modes that only move it: along x (``shift_std``: each vertex moves
    that far at one standard deviation) and about z through the centroid (``turn_std`` radians), and
    its own shape modes less any rigid motion."""
    template = embedded_model.template
    fields = rigid_fields(template)
    along_x, about_z = fields[:, 0], fields[:, 5]
    shape = without_rigid_motion(embedded_model)
    moves = np.stack([shift_std * along_x, turn_std * about_z], axis=1)
    modes = np.concatenate([moves, shape.basis * shape.std], axis=1)
    return model_from_arrays(template, embedded_model.faces, modes.reshape(-1, 3, modes.shape[1]))


def test_the_distance_is_the_move_in_standard_deviations_of_the_modes_rigid_motion(embedded_model):
    model = rigid_model(embedded_model, 0.02, 0.01)
    turn = Rotation.from_rotvec([0.0, 0.0, 0.03]).as_matrix()
    assert rigid_motion_distance(model, np.eye(3), np.zeros(3)) == 0.0
    assert rigid_motion_distance(model, np.eye(3), [0.05, 0.0, 0.0]) == pytest.approx(2.5, rel=1e-6)
    assert rigid_motion_distance(model, turn, np.zeros(3)) == pytest.approx(3.0, rel=1e-6)
    assert rigid_motion_distance(model, turn, [-0.08, 0.0, 0.0]) == pytest.approx(5.0, rel=1e-6)
    # in other units (the model ten times larger) the move ten times larger is as far
    large = model_from_arrays(10 * model.template, model.faces,
                              (10 * model.basis * model.std).reshape(-1, 3, model.num_modes))
    assert rigid_motion_distance(large, turn, [-0.8, 0.0, 0.0]) == pytest.approx(5.0, rel=1e-6)
    # a move the modes never make is far, however small
    assert rigid_motion_distance(model, np.eye(3), [0.0, 1e-3, 0.0]) > 100 * OFF_ITS_PLACE


@pytest.mark.filterwarnings("ignore:.*rigid motion")     # the 98% model's own rule says so
def test_the_alignment_decides_only_for_a_partly_rigid_model_under_auto_with_a_pose_to_find(embedded_model):
    def alignment_decides(model, rigid_modes: str, finds_pose: bool) -> bool:
        return fitting_model_and_rule(model, rigid_modes, finds_pose)[1] is not None

    assert alignment_decides(embedded_model, "auto", finds_pose=True)            # 12% rigid
    assert not alignment_decides(embedded_model, "auto", finds_pose=False)       # no alignment
    assert not alignment_decides(embedded_model, "keep", finds_pose=True)
    assert not alignment_decides(embedded_model, "drop", finds_pose=True)        # dropped before
    assert not alignment_decides(moving_head(embedded_model), "auto", finds_pose=True)     # 98%: dropped before
    assert not alignment_decides(moving_head(embedded_model, 1.0), "auto", finds_pose=True)   # 74%, as bodies: kept
    assert not alignment_decides(without_rigid_motion(embedded_model), "auto", finds_pose=True)   # none to drop


def scene(model, turn_deg: float, shift: float, size: int = 48):
    """A normal map of a sample of ``model`` turned by ``turn_deg`` about a tilted vertical axis and
    moved by ``shift`` of its RMS radius, and its camera."""
    from statfit.renderer.images import render_target
    from statfit.structures.normal_map import NormalMap
    from statfit.synth.sample import camera_for_view

    shape = model.sample(np.random.default_rng(3), 1.0)
    centre = shape.mean(axis=0)
    radius = float(np.sqrt(((shape - centre) ** 2).sum(axis=1).mean()))
    axis = np.array([0.3, 0.9, 0.3]) / np.linalg.norm([0.3, 0.9, 0.3])
    shape = Rotation.from_rotvec(np.radians(turn_deg) * axis).apply(shape - centre) + centre
    shape = shape + shift * radius * np.array([1.0, -0.5, 0.0])
    camera = camera_for_view(shape, 20.0, 5.0, size)
    return NormalMap(*render_target(shape, model.faces, camera)), camera


def test_render_fits_without_the_rigid_motion_only_where_the_alignment_moved_the_model_off_its_place(
        embedded_model, monkeypatch):
    import statfit.render.job as job
    from statfit.core.settings import FitSpace
    from statfit.errors import StatfitWarning
    from statfit.render.job import posed_view, reconstruct
    from statfit.render.many import reconstruct_many

    monkeypatch.setattr(job, "POSE_ITERATIONS", 40)     # the alignment's steps, cut for time: it still moves far
    model = embedded_model
    cpu = torch.device("cpu")
    placed, misplaced = scene(model, 0.0, 0.0), scene(model, 8.0, 0.06)
    # misplaced: aligned again, and fitted, without the modes' rigid motion
    with pytest.warns(StatfitWarning, match=r"standard deviations of its modes' rigid motion off where they place"):
        view = posed_view(model, fitting_model_and_rule(model, "auto", True)[1], *misplaced, cpu, torch.float32)
    assert view.rigid_free
    freed = FitSpace.of(without_rigid_motion(model), model.frame)
    np.testing.assert_array_equal(view.space.basis_t.numpy(), freed.basis_t.numpy())
    np.testing.assert_array_equal(view.space.std.numpy(), freed.std.numpy())
    # fitted together with a map placed where the model places its people (the alignment keeps the
    # start): that one as built, silently; the misplaced one with its own modes and its own warning
    together = reconstruct_many(model, [placed[0], misplaced[0]], [placed[1], misplaced[1]], "pca", iterations=10)
    assert together[0].warnings == [] and "rigid motion" in together[1].warnings[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        kept = reconstruct(model, *placed, "pca", iterations=10, rigid_modes="keep").vertices
        kept_misplaced = reconstruct(model, *misplaced, "pca", iterations=10, rigid_modes="keep").vertices
    np.testing.assert_allclose(together[0].fit.vertices, kept, rtol=0, atol=1e-9)
    with pytest.warns(StatfitWarning, match="rigid motion"):
        alone = reconstruct(model, *misplaced, "pca", iterations=10)
    np.testing.assert_allclose(together[1].fit.vertices, alone.vertices, rtol=0, atol=1e-9)
    assert np.abs(alone.vertices - kept_misplaced).max() > 1e-4
