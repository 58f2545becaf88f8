"""A model's modes without rigid motion (statfit.model.cut.without_rigid_motion), against the
closed form: each mode less its least-squares small rigid motion, the covariance's square root by
SVD."""
from __future__ import annotations

import json
import warnings

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
    for path, says in ((tmp_path / "moving.npz", "fits keep it"), (tmp_path / "face.npz", "closed form moves the pose")):
        code, out, err = run(["model", "info", str(path)], capsys)
        assert code == 0 and says in " ".join(out.replace("│", " ").split()), out    # the table's cells wrap


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


def moving_head(model, size: float = 4.0):
    """The embedded head with a mode that shifts it and one that turns it added (rigid share 0.98;
    ``size`` 1: 0.74): a part cut from a larger model, as MakeHuman's head is."""
    fields = rigid_fields(model.template)
    moves = fields[:, [1, 3]] / np.linalg.norm(fields[:, [1, 3]], axis=0) * [0.5 * size, 0.4 * size]
    modes = np.concatenate([moves, model.basis * model.std], axis=1).reshape(-1, 3, model.num_modes + 2)
    return model_from_arrays(model.template, model.faces, modes, model.landmarks, model.regions)


def test_auto_fits_a_mostly_rigid_model_without_its_rigid_motion_and_any_other_as_given(embedded_model):
    from statfit.errors import StatfitError, StatfitWarning
    from statfit.model.cut import fitting_model, rigid_motion_share

    moving = moving_head(embedded_model)
    share = rigid_motion_share(moving)
    assert share > 0.9 > rigid_motion_share(moving_head(embedded_model, 1.0)) > 0.7
    with pytest.warns(StatfitWarning, match=f"{100 * share:.1f}% of the model's modes' variance is rigid motion"):
        chosen = fitting_model(moving)
    freed = without_rigid_motion(moving)
    np.testing.assert_array_equal(chosen.basis, freed.basis)
    np.testing.assert_array_equal(chosen.std, freed.std)
    assert fitting_model(moving, "keep") is moving
    np.testing.assert_array_equal(fitting_model(embedded_model, "drop").std, without_rigid_motion(embedded_model).std)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert fitting_model(embedded_model) is embedded_model     # 12% rigid: as given, silently
        mostly = moving_head(embedded_model, 1.0)
        assert fitting_model(mostly) is mostly                     # 74%, as MakeHuman's whole body: as given
        rigid_only = model_from_arrays(embedded_model.template, embedded_model.faces,
                                       rigid_fields(embedded_model.template)[:, [0, 4]].reshape(-1, 3, 2))
        assert fitting_model(rigid_only) is rigid_only             # nothing would be left: as given
    with pytest.raises(StatfitError, match="unknown --rigid-modes 'none'; choose one of auto, keep, drop"):
        fitting_model(moving, "none")


def test_register_and_render_fit_the_model_the_rule_chooses(embedded_model):
    """A mostly rigid model fitted with the default is, to the bit, its rigid-free model fitted as
    given; kept as built it ends elsewhere; and so does the default where the scan is taken to lie
    in the model's frame."""
    from conftest import normal_map_scene
    from statfit.errors import StatfitWarning
    from statfit.registration.job import register
    from statfit.render.job import reconstruct
    from statfit.synth.sample import sample_target, scan_from_view

    moving = moving_head(embedded_model)
    freed = without_rigid_motion(moving)
    rng = np.random.default_rng(3)
    points = scan_from_view(sample_target(embedded_model, rng), embedded_model.faces, rng, 1500, 20.0)
    with pytest.warns(StatfitWarning, match="rigid motion"):
        fits = {name: register(model, points, "pca", align="rigid", iterations=20, rigid_modes=rule).vertices
                for name, model, rule in (("auto", moving, "auto"), ("freed", freed, "keep"), ("kept", moving, "keep"))}
    np.testing.assert_array_equal(fits["auto"], fits["freed"])
    assert np.abs(fits["kept"] - fits["auto"]).max() > 1e-4
    # a scan taken to lie in the model's frame (no alignment, no landmarks): nothing else finds the
    # pose, so the modes keep their rigid motion
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        in_frame = {rule: register(moving, points, "pca", align="none", iterations=20, rigid_modes=rule).vertices
                    for rule in ("auto", "keep")}
    np.testing.assert_array_equal(in_frame["auto"], in_frame["keep"])
    normal_map, camera = normal_map_scene(embedded_model, 48)[:2]
    with pytest.warns(StatfitWarning, match="rigid motion"):
        renders = {name: reconstruct(model, normal_map, camera, "pca", iterations=10, rigid_modes=rule).vertices
                   for name, model, rule in (("auto", moving, "auto"), ("freed", freed, "keep"))}
    np.testing.assert_array_equal(renders["auto"], renders["freed"])


def test_the_cli_says_which_modes_it_fits_and_refuses_an_unknown_rule(tmp_path, embedded_model, capsys):
    from statfit.io.mesh import points_bytes
    from statfit.model.statmodel import save_model
    from statfit.synth.sample import sample_target, scan_from_view

    save_model(moving_head(embedded_model), tmp_path / "moving.npz")
    rng = np.random.default_rng(4)
    (tmp_path / "scan.ply").write_bytes(points_bytes(scan_from_view(sample_target(embedded_model, rng),
                                                                    embedded_model.faces, rng, 1500, 20.0)))
    fit = ["register", str(tmp_path / "scan.ply"), "--model", str(tmp_path / "moving.npz"), "--method", "pca",
           "--align", "rigid", "--iterations", "5", "-q"]
    code, _, err = run([*fit, "-o", str(tmp_path / "a.ply")], capsys)
    assert code == 0 and "of the model's modes' variance is rigid motion" in err, err
    code, _, err = run([*fit, "-o", str(tmp_path / "b.ply"), "--rigid-modes", "keep"], capsys)
    assert code == 0 and "rigid motion" not in err, err
    for command in (fit + ["-o", str(tmp_path / "c.ply")],
                    ["batch", "register", str(tmp_path / "scan.ply"), "--out-dir", str(tmp_path / "out"),
                     "--model", str(tmp_path / "moving.npz")]):
        code, _, err = run([*command, "--rigid-modes", "off"], capsys)
        assert code == 2 and err.strip() == "statfit: error: unknown --rigid-modes 'off'; choose one of auto, keep, drop"
    assert not (tmp_path / "c.ply").exists() and not (tmp_path / "out").exists()
