"""An output named for another format is refused before any work, in one line: its bytes would
open nowhere under that name (a model's npz in `mask.ply`, an EXR in `normals.png`)."""
from __future__ import annotations

import pytest

from test_cli import run

CASES = [
    (["model", "build", "a.ply", "b.ply", "-o", "model.ply"], "model.ply: a model is written as .npz, not .ply"),
    (["model", "cut", "model.npz", "--region", "face", "-o", "mask.ply"], "mask.ply: a model is written as .npz"),
    (["model", "import", "generic_model.pkl", "-o", "flame"],
     "flame: a model is written as .npz, not a name without a suffix"),
    (["model", "build-makehuman", "makehuman", "-o", "body.obj"], "body.obj: a model is written as .npz, not .obj"),
    (["model", "build-texture", "a.png", "-o", "tex.png"], "tex.png: a texture model is written as .npz, not .png"),
    (["synth", "normals", "--out", "normals.png"], "normals.png: a normal map is written as .exr, not .png"),
    (["synth", "scan", "--out", "scan.obj"], "scan.obj: point clouds are written as .ply or as text"),
    (["synth", "scan", "--realistic", "--out", "scan.xyz"], "scan.xyz: meshes are written as .ply or .obj"),
    (["register", "scan.ply", "--preview", "fit.jpg"], "fit.jpg: a preview is written as .png, not .jpg"),
    (["render", "normals.exr", "--preview", "fit.jpg"], "fit.jpg: a preview is written as .png"),
    (["inpaint", "face.png", "--mask", "holes.png", "--preview", "p.exr"], "p.exr: a preview is written as .png"),
    (["splat", "views", "--splats", "splats.txt"], "splats.txt: a splat file is written as .ply, not .txt"),
    (["splat", "views", "--preview", "p.jpg"], "p.jpg: a preview is written as .png"),
]


@pytest.mark.parametrize("argv, message", CASES, ids=[" ".join(argv[:2]) + " " + argv[-1] for argv, _ in CASES])
def test_an_output_named_for_another_format_is_refused_first(tmp_path, monkeypatch, capsys, argv, message):
    monkeypatch.chdir(tmp_path)
    code, _, err = run(argv, capsys)
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert list(tmp_path.iterdir()) == []
