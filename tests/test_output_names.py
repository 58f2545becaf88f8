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


OVERWRITES = [
    (["register", "scan.ply", "--out", "scan.ply"], "--out scan.ply is the scan: statfit never writes over its input"),
    (["register", "link.ply", "--out", "scan.ply"], "--out scan.ply is the scan"),
    (["register", "scan.ply", "--out", "fit.ply", "--log", "./fit.ply"], "--out and --log both name fit.ply"),
    (["register", "scan.ply", "--landmarks", "marks.txt", "--out", "fit.ply", "--log", "marks.txt"],
     "--log marks.txt is the landmark file"),
    (["render", "map.png", "--camera", "cam.json", "--out", "fit.ply", "--preview", "map.png"],
     "--preview map.png is the normal map"),
    (["synth", "normals", "--shape", "shape.ply", "--out", "n.exr", "--gt", "shape.ply"], "--gt shape.ply is the shape"),
    (["inpaint", "face.png", "--mask", "holes.png", "--out", "holes.png"], "--out holes.png is the mask"),
]


@pytest.mark.parametrize("argv, message", OVERWRITES, ids=[" ".join(argv) for argv, _ in OVERWRITES])
def test_an_output_that_names_an_input_or_another_output_is_refused_first(tmp_path, monkeypatch, capsys, argv,
                                                                           message):
    """Never a changed input: an output naming an input (by any path, a link too) or another output
    is refused in one line before any work, and every file stays as it was."""
    monkeypatch.chdir(tmp_path)
    for name in ("scan.ply", "marks.txt", "map.png", "cam.json", "shape.ply", "face.png", "holes.png"):
        (tmp_path / name).write_bytes(name.encode())
    (tmp_path / "link.ply").symlink_to(tmp_path / "scan.ply")
    before = {path.name: path.read_bytes() for path in tmp_path.iterdir()}
    code, _, err = run(argv, capsys)
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert {path.name: path.read_bytes() for path in tmp_path.iterdir()} == before
