"""``statfit synth views`` → ``splat`` → ``splat-render`` → ``eval`` end to end on the embedded model,
bad input to them (one line, exit 2, nothing written), and the objective's pieces (SSIM, view
order) against closed forms."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import run_cli
from statfit.io.image import read_image, write_image
from statfit.io.mesh import read_mesh
from statfit.objectives.images import ImageObjective, TrainingView, psnr, ssim
from statfit.renderer import MeshSplats
from statfit.synth.views import held_out_split, hemisphere_cameras


@pytest.fixture(scope="module")
def views(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("splat") / "views"
    code, err = run_cli(["synth", "views", "--views", "6", "--size", "48", "--test-every", "3", "--seed", "1",
                         "--out", str(folder)])
    assert code == 0, err
    return folder


def test_synth_views_writes_photographs_cameras_and_the_truth(views):
    manifest = json.loads((views / "cameras.json").read_text())
    assert [v["split"] for v in manifest["views"]] == ["train", "train", "test", "train", "train", "test"]
    image = read_image(views / manifest["views"][0]["image"])
    assert image.shape == (48, 48, 4)
    alpha = image[..., 3]
    assert 0.05 < (alpha > 0.5).mean() < 0.9 and image[..., :3][alpha > 0.99].mean() > 0.2  # a lit, textured head
    assert read_mesh(views / "gt.ply")[0].shape == (4842, 3)


def test_a_coarse_model_gets_photographs_too():
    """A model of fewer vertices than the albedo has spots (80) was an internal failure ("Cannot take
    a larger sample than population"): now a spot on each vertex at most. A tetrahedron: a colour
    per vertex, in range, not all alike."""
    from statfit.synth.views import generated_albedo

    vertices = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
    colour = generated_albedo(vertices, np.random.default_rng(0))
    assert colour.shape == (4, 3) and (colour >= 0.02).all() and (colour <= 0.98).all()
    assert np.ptp(colour, axis=0).min() > 0.01


def test_cameras_cover_the_front_hemisphere():
    cameras = hemisphere_cameras(np.random.default_rng(0).normal(size=(50, 3)), 24, 32)
    towards = np.stack([c.center.numpy() for c in cameras])
    towards /= np.linalg.norm(towards, axis=1, keepdims=True)
    angles = np.degrees(np.arccos(np.clip(towards @ [0, 0, 1], -1, 1)))
    assert angles.max() <= 70.5 and angles.min() < 15        # within 70° of the front, one nearly frontal
    assert (towards[:, 0] > 0.3).any() and (towards[:, 0] < -0.3).any() and (towards[:, 1] > 0.3).any()
    assert held_out_split(24, 6).count("test") == 4 and held_out_split(5, 0) == ["train"] * 5


def test_splat_fits_renders_and_scores_held_out_views(views, tmp_path):
    out = tmp_path / "fit.ply"
    code, err = run_cli(["splat", str(views), "--iterations", "60", "-q", "--out", str(out), "--splats",
                         str(tmp_path / "splats.ply"), "--preview", str(tmp_path / "p.png"), "--log",
                         str(tmp_path / "log.jsonl")])
    assert code == 0, err
    summary = json.loads((tmp_path / "log.jsonl").read_text().splitlines()[-1])
    assert summary["held_out"]["views"] == 2 and summary["held_out"]["psnr"] > 20
    assert read_mesh(out)[0].shape == (4842, 3)
    code, err = run_cli(["splat-render", str(tmp_path / "splats.ply"), str(out), "--camera",
                         str(views / "cameras.json"), "--view", "2", "--out", str(tmp_path / "novel.png")])
    assert code == 0, err
    novel = read_image(tmp_path / "novel.png")
    photo = read_image(views / "view_002.png")
    assert novel.shape == photo.shape
    # the held-out view rendered by splat-render scores what splat reported for it
    reported = summary["views"]["view_002.png"]["psnr"]
    assert psnr(torch.tensor(novel[..., :3]), torch.tensor(photo[..., :3])) == pytest.approx(reported, abs=0.3)
    code, err = run_cli(["eval", str(out), str(views / "gt.ply")])
    assert code == 0, err


def _copy(views: Path, tmp_path: Path) -> Path:
    target = tmp_path / "views"
    shutil.copytree(views, target)
    return target


def _edit_manifest(folder: Path, change) -> Path:
    manifest = json.loads((folder / "cameras.json").read_text())
    change(manifest)
    (folder / "cameras.json").write_text(json.dumps(manifest))
    return folder


BAD_FOLDERS = {
    "no cameras.json": (lambda f: (f / "cameras.json").unlink() or f, "cameras.json"),
    "no views": (lambda f: _edit_manifest(f, lambda m: m.update(views=[])), "no views"),
    "a missing camera": (lambda f: _edit_manifest(f, lambda m: m["views"][1].pop("camera")), "camera"),
    "an image of another size": (lambda f: write_image(f / "view_001.png", np.ones((40, 40, 4), np.float32)) or f,
                                 "the image is 40×40 but its camera 48×48"),
    "views of different sizes": (lambda f: _edit_manifest(f, lambda m: m["views"][1]["camera"].update(width=40)),
                                 "same size"),
    "an empty mask": (lambda f: write_image(f / "view_001.png", np.zeros((48, 48, 4), np.float32)) or f,
                      "mask is empty"),
    "a missing image": (lambda f: (f / "view_003.png").unlink() or f, "view_003.png"),
    "every view held out": (lambda f: _edit_manifest(f, lambda m: [v.update(split="test") for v in m["views"]]),
                            "train"),
}


@pytest.mark.parametrize("case", BAD_FOLDERS)
def test_bad_view_folders_are_refused_in_one_line(views, tmp_path, case):
    make, words = BAD_FOLDERS[case]
    folder = make(_copy(views, tmp_path))
    out = tmp_path / "out"
    out.mkdir()
    code, err = run_cli(["splat", str(folder), "--iterations", "2", "-q", "--out", str(out / "fit.ply"),
                         "--splats", str(out / "s.ply")])
    assert code == 2 and err.startswith("statfit: error:") and err.count("\n") == 1, err
    assert words in err and not any(out.iterdir())


@pytest.mark.parametrize("argv, words", [
    (["synth", "views", "--views", "0"], "views"),
    (["synth", "views", "--views", "3", "--test-every", "1"], "training"),
    (["splat", "VIEWS", "--per-triangle", "2"], "per-triangle"),
    (["splat", "VIEWS", "--views-per-step", "5"], "training views"),
    (["splat", "VIEWS", "--method", "regularized"], "unknown method"),
])
def test_bad_options_are_refused_before_any_work(views, tmp_path, argv, words):
    argv = [str(views) if a == "VIEWS" else a for a in argv] + ["--out", str(tmp_path / "o")]
    code, err = run_cli(argv)
    assert code == 2 and words in err and err.count("\n") == 1, err
    assert not any(tmp_path.iterdir())


def test_splat_render_refuses_splats_of_another_mesh(views, tmp_path):
    code, _ = run_cli(["splat", str(views), "--iterations", "1", "-q", "--out", str(tmp_path / "fit.ply"),
                       "--splats", str(tmp_path / "s.ply")])
    assert code == 0
    vertices, faces = read_mesh(tmp_path / "fit.ply")
    import trimesh
    trimesh.Trimesh(vertices, faces[:-10], process=False).export(tmp_path / "smaller.ply")
    code, err = run_cli(["splat-render", str(tmp_path / "s.ply"), str(tmp_path / "smaller.ply"), "--camera",
                         str(views / "cameras.json"), "--view", "0", "--out", str(tmp_path / "r.png")])
    assert code == 2 and "faces" in err and not (tmp_path / "r.png").exists()
    code, err = run_cli(["splat-render", str(tmp_path / "s.ply"), str(tmp_path / "fit.ply"), "--camera",
                         str(views / "cameras.json"), "--out", str(tmp_path / "r.png")])
    assert code == 2 and "--view" in err


def test_ssim_and_psnr_closed_forms():
    rng = np.random.default_rng(0)
    image = torch.tensor(rng.uniform(size=(32, 32, 3)))
    assert float(ssim(image, image)) == pytest.approx(1.0, abs=1e-9)
    assert float(ssim(image, 1 - image)) < 0.0                       # anti-correlated structure
    assert psnr(image, image + 0.1) == pytest.approx(20.0, abs=1e-6)  # −10 log10(0.01)
    # a constant image against another: only the luminance term differs (zero padding changes the
    # 5-pixel border, 2.5% here)
    a, b = torch.full((256, 256, 3), 0.2, dtype=torch.float64), torch.full((256, 256, 3), 0.6, dtype=torch.float64)
    c1 = 0.01**2
    assert float(ssim(a, b)) == pytest.approx((2 * 0.2 * 0.6 + c1) / (0.2**2 + 0.6**2 + c1), rel=0.03)


def test_every_training_view_is_used_once_per_pass():
    faces = torch.tensor([[0, 1, 2]])
    views = [TrainingView(None, torch.zeros(4, 4, 3), None) for _ in range(5)]
    objective = ImageObjective(views, MeshSplats.on(faces), views_per_step=2)
    chosen = []
    for iteration in range(5):
        objective.prepare(torch.zeros(3, 3), iteration)
        chosen += objective._chosen
    assert sorted(chosen[:5]) == [0, 1, 2, 3, 4] and len(chosen) == 10
