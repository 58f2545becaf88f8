"""`statfit register --preview`: the scan on the fit and where the fit guessed, as a picture; its
pixel functions against closed forms; a bad preview option refused before any work."""
from __future__ import annotations

import matplotlib
import numpy as np
import pytest
import torch
from PIL import Image

from statfit.renderer.images import FAR_SHARE, front_camera, mesh_with_points
from test_cli import run

VIRIDIS = matplotlib.colormaps["viridis"](np.linspace(0.0, 1.0, 256))[:, :3] * 255


def _field_panels(png) -> list[np.ndarray]:
    """The preview's field views, left to right: each a column band's pixels read back through
    viridis as values in [0, 1] (NaN: not a viridis colour), every second pixel."""
    with Image.open(png) as image:
        pixels = np.asarray(image.convert("RGB"), dtype=np.float64)[40::2, ::2]   # below the titles
    distance = np.linalg.norm(pixels[:, :, None, :] - VIRIDIS[None, None], axis=-1)     # (H, W, 256)
    value = np.where(distance.min(axis=-1) < 12, distance.argmin(axis=-1) / 255, np.nan)
    columns = np.isfinite(value).any(axis=0)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], columns.astype(int), [0]])))
    bands = [(start, stop) for start, stop in zip(edges[::2], edges[1::2]) if stop - start > 20]   # not the bar
    return [value[:, start:stop] for start, stop in bands]


def test_the_preview_shows_the_seen_side_near_the_scan_and_the_far_side_guessed(scan_files, tmp_path, capsys):
    scan, _ = scan_files
    fit, preview = tmp_path / "fit.ply", tmp_path / "fit.png"
    code, _, err = run(["register", str(scan), "--out", str(fit), "--preview", str(preview), "--iterations", "30",
                        "-q"], capsys)
    assert code == 0, err
    front, turned, behind = _field_panels(preview)
    # data_distance, the default: ~0 where the scan (a view of the face) saw the fit, large behind.
    assert np.nanmean(front) < 0.1 and np.nanmean(behind) > 0.4, (np.nanmean(front), np.nanmean(behind))
    assert np.isfinite(front).sum() > 1000 and np.isfinite(behind).sum() > 1000
    code, _, err = run(["register", str(scan), "--out", str(fit), "--preview", str(preview), "--iterations", "30",
                        "--preview-colour", "normals", "-q"], capsys)
    assert code == 0, err
    assert _field_panels(preview) == []      # shaded by normals: no field, no colour bar


def test_points_on_the_mesh_are_green_and_points_off_it_red():
    """A square facing the camera; points on it, and points 2·FAR_SHARE of its RMS radius in front
    of it: drawn where the camera projects them, green and red."""
    vertices = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    camera = front_camera(vertices, np.eye(3), 64)
    radius = np.sqrt(2.0)
    points = np.array([[0.5, 0.5, 0.0], [-0.5, -0.3, 2 * FAR_SHARE * radius]])
    image, shown = mesh_with_points(vertices, faces, points, np.array([0.0, 2 * FAR_SHARE * radius]), camera)
    pixels = camera.project(torch.as_tensor(points))[0].numpy()
    (column_on, row_on), (column_off, row_off) = np.floor(pixels).astype(int)
    np.testing.assert_allclose(image[row_on, column_on], [0.1, 0.7, 0.2])
    np.testing.assert_allclose(image[row_off, column_off], [0.9, 0.1, 0.1])
    assert shown[row_on, column_on] and shown.sum() > 0.3 * 64 * 64       # the square fills its frame
    assert (image[0, 0] == 1.0).all()                                      # white around it


@pytest.mark.parametrize("arguments, message", [
    (["--preview", "fit.jpg"], "fit.jpg: a preview is written as .png, not .jpg"),
    (["--preview", "fit.png", "--preview-colour", "depth"], "unknown --preview-colour 'depth'"),
])
@pytest.mark.parametrize("command", ["register", "render"])
def test_a_bad_preview_is_refused_before_any_work(tmp_path, capsys, monkeypatch, command, arguments, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "input").write_bytes(b"not read: the options are refused first")
    code, _, err = run([command, "input", "--out", "fit.ply", *arguments], capsys)
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert sorted(path.name for path in tmp_path.iterdir()) == ["input"]
