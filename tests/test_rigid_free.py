"""A model's modes without rigid motion (statfit.model.cut.without_rigid_motion), against the
closed form: each mode less its least-squares small rigid motion, the covariance's square root by
SVD."""
from __future__ import annotations

import json

import numpy as np
import pytest

from statfit.model.cut import without_rigid_motion
from statfit.model.statmodel import model_from_arrays
from test_cli import run


def rigid_fields(template: np.ndarray) -> np.ndarray:
    """(3N, 6): translations along x, y, z and small rotations about them through the centroid."""
    centred = template - template.mean(axis=0)
    fields = [np.tile(axis, (len(template), 1)) for axis in np.eye(3)] + [np.cross(axis, centred) for axis in np.eye(3)]
    return np.stack([field.reshape(-1) for field in fields], axis=1)


def less_rigid(fields: np.ndarray, modes: np.ndarray) -> np.ndarray:
    """``modes`` (3N, K) less their least-squares fit by the ``fields`` (solved, not projected)."""
    return modes - fields @ np.linalg.lstsq(fields, modes, rcond=None)[0]


def test_modes_that_only_move_the_model_go_and_a_shape_mode_stays(embedded_model):
    template, faces = embedded_model.template, embedded_model.faces
    fields = rigid_fields(template)
    shape = less_rigid(fields, np.random.default_rng(0).normal(size=(template.size, 1)))[:, 0]
    shape /= np.linalg.norm(shape)
    modes = np.stack([3.0 * fields[:, 0], 0.5 * shape, 2.0 * fields[:, 5] / np.linalg.norm(fields[:, 5])], axis=1)
    moving = model_from_arrays(template, faces, modes.reshape(-1, 3, 3))
    assert moving.num_modes == 3
    freed = without_rigid_motion(moving)
    assert freed.num_modes == 1 and freed.std[0] == pytest.approx(0.5, rel=1e-9)
    assert abs(float(freed.basis[:, 0] @ shape)) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_array_equal(freed.template, template)


def test_the_modes_are_the_square_root_of_the_covariance_without_rigid_motion(embedded_model):
    model = embedded_model
    fields = rigid_fields(model.template)
    # some rigid motion added to every mode: it goes, and what is left is as before
    moved = model.basis * model.std + fields @ np.random.default_rng(1).normal(scale=0.01, size=(6, model.num_modes))
    expected = less_rigid(fields, moved)
    freed = without_rigid_motion(model_from_arrays(model.template, model.faces, moved.reshape(-1, 3, model.num_modes),
                                                   model.landmarks, model.regions))
    np.testing.assert_allclose(freed.std, np.linalg.svd(expected, compute_uv=False), rtol=1e-9)
    np.testing.assert_allclose(freed.basis @ (freed.basis.T @ expected), expected, atol=1e-12)
    assert np.abs(freed.basis.T @ fields).max() < 1e-10
    np.testing.assert_allclose(freed.std, without_rigid_motion(model).std, rtol=1e-9)
    np.testing.assert_array_equal(freed.landmarks, model.landmarks)
    assert freed.regions.keys() == model.regions.keys()


def test_model_cut_takes_a_parts_rigid_motion_out_and_info_shows_the_share(tmp_path, embedded_model, capsys):
    """A part whose modes mostly move it, as a head cut from a body model: the embedded head with
    two modes that shift and turn it added, cut with --without-rigid-motion; `model info` reports
    each one's rigid share."""
    from statfit.model.cut import rigid_motion_share
    from statfit.model.statmodel import load_model, save_model

    model = embedded_model
    fields = rigid_fields(model.template)
    moves = fields[:, [1, 3]] / np.linalg.norm(fields[:, [1, 3]], axis=0) * [0.5, 0.4]    # a shift and a turn
    modes = np.concatenate([moves, model.basis * model.std], axis=1).reshape(-1, 3, model.num_modes + 2)
    moving = model_from_arrays(model.template, model.faces, modes, model.landmarks, model.regions)
    expected = 1.0 - (less_rigid(fields, moving.basis * moving.std) ** 2).sum() / (moving.std**2).sum()
    assert rigid_motion_share(moving) == pytest.approx(expected, rel=1e-9) and expected > 0.7
    save_model(moving, tmp_path / "moving.npz")
    code, out, err = run(["model", "cut", str(tmp_path / "moving.npz"), "--region", "face", "--without-rigid-motion",
                          "-o", str(tmp_path / "face.npz"), "--json"], capsys)
    assert code == 0, err
    face = load_model(tmp_path / "face.npz")
    assert rigid_motion_share(face) < 1e-12 and face.num_modes == json.loads(out)["modes"] <= model.num_modes + 2
    for path, share in ((tmp_path / "moving.npz", expected), (tmp_path / "face.npz", 0.0)):
        code, out, err = run(["model", "info", str(path), "--json"], capsys)
        assert code == 0 and json.loads(out)["rigid_motion_share"] == pytest.approx(share, abs=1e-9), out


def test_a_model_whose_modes_only_move_it_is_refused_in_one_line(tmp_path, embedded_model, capsys):
    """Nothing but rigid motion in its modes: no model is left, so `model cut --without-rigid-motion`
    says so and writes nothing (not a model of rounding noise)."""
    from statfit.model.statmodel import save_model

    fields = rigid_fields(embedded_model.template)[:, [0, 4]]
    save_model(model_from_arrays(embedded_model.template, embedded_model.faces, fields.reshape(-1, 3, 2)),
               tmp_path / "rigid.npz")
    code, out, err = run(["model", "cut", str(tmp_path / "rigid.npz"), "--without-rigid-motion", "-o",
                          str(tmp_path / "out.npz")], capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "only move it rigidly" in lines[0], err
    assert not (tmp_path / "out.npz").exists()
