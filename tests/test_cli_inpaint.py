"""`statfit model build-texture` → `statfit inpaint` end to end, and bad input to them (one line,
exit 2, nothing written, inputs unchanged)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from statfit.io.image import read_image, write_image
from texture_fixtures import brow_hole, face_textures
from test_cli import corrupt, run

SIZE = 32
FAST = ["--iterations", "40", "-q"]


@pytest.fixture(autouse=True)
def _threads():
    """One thread: small images (see tests/test_inpaint.py)."""
    torch.set_num_threads(1)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """30 generated textures in a folder, a held-out face, its mask, and a model built by the CLI."""
    folder = tmp_path_factory.mktemp("textures")
    textures = face_textures(31, SIZE, seed=2)
    (folder / "train").mkdir()
    for i, texture in enumerate(textures[:-1]):
        write_image(folder / "train" / f"{i:02d}.png", texture)
    write_image(folder / "face.png", textures[-1])
    write_image(folder / "holes.png", brow_hole(SIZE)[..., None].astype(np.float32))
    with pytest.raises(SystemExit) as exit_info:
        from statfit_cli.main import main
        main(["model", "build-texture", str(folder / "train"), "-o", str(folder / "tex.npz"), "--k", "20",
              "--size", str(SIZE), "-q"])
    assert exit_info.value.code == 0
    return folder


def test_build_texture_then_inpaint(files, tmp_path, capsys):
    out, log, preview = tmp_path / "filled.png", tmp_path / "fill.jsonl", tmp_path / "preview.png"
    code, stdout, err = run(["inpaint", str(files / "face.png"), "--mask", str(files / "holes.png"), "--model",
                             str(files / "tex.npz"), "--out", str(out), "--log", str(log), "--preview", str(preview),
                             "--json", *FAST], capsys)
    assert code == 0, err
    summary = json.loads(stdout)
    assert summary["method"] == "hybrid" and summary["iterations"] == 40
    assert summary["hole_pixels"] == int((~brow_hole(SIZE)).sum())
    lines = [json.loads(line) for line in log.read_text().splitlines()]
    assert [lines[0]["type"], lines[-1]["type"]] == ["header", "summary"] and {"data", "elapsed"} <= set(lines[1])
    assert lines[0]["settings"]["beta"] == 30.0 and lines[0]["modes"] == 20
    face, filled = read_image(files / "face.png"), read_image(out)
    visible = brow_hole(SIZE)
    assert filled.shape == face.shape
    np.testing.assert_array_equal(filled[visible], face[visible])       # visible pixels are the input's
    assert np.abs(filled[~visible] - face[~visible]).mean() < 0.1
    with Image.open(preview) as image:
        assert image.format == "PNG" and image.size[0] > 3 * image.size[1] * 0.9


def test_laplacian_baseline_needs_no_model_and_writes_exr(files, tmp_path, capsys):
    out = tmp_path / "blurry.exr"
    code, stdout, err = run(["inpaint", str(files / "face.png"), "--mask", str(files / "holes.png"), "--method",
                             "laplacian", "--lam", "99", "--out", str(out), "--json", *FAST], capsys)
    assert code == 0, err
    assert json.loads(stdout)["method"] == "laplacian"
    assert read_image(out).shape == (SIZE, SIZE, 3)


def test_mask_invert_and_charts(files, tmp_path, capsys):
    holes_white = tmp_path / "white_holes.png"
    write_image(holes_white, (~brow_hole(SIZE))[..., None].astype(np.float32))
    charts = tmp_path / "charts.png"
    write_image(charts, np.ones((SIZE, SIZE, 3), np.float32))
    outputs = []
    for name, mask_args in (("a.png", ["--mask", str(files / "holes.png")]),
                            ("b.png", ["--mask", str(holes_white), "--mask-invert", "--charts", str(charts)])):
        code, _, err = run(["inpaint", str(files / "face.png"), *mask_args, "--model", str(files / "tex.npz"),
                            "--out", str(tmp_path / name), *FAST], capsys)
        assert code == 0, err
        outputs.append(read_image(tmp_path / name))
    # One chart covering the whole image is no restriction: the same result.
    np.testing.assert_array_equal(outputs[0], outputs[1])


def test_build_texture_from_globs_with_jitter(files, tmp_path, capsys):
    code, stdout, err = run(["model", "build-texture", str(files / "train" / "0*.png"), str(files / "face.png"),
                             "-o", str(tmp_path / "m.npz"), "--k", "50", "--size", "16x24", "--jitter", "2",
                             "--json", "-q"], capsys)
    assert code == 0
    summary = json.loads(stdout)
    assert summary["textures"] == 11 and summary["samples"] == 33 and summary["modes"] == 32
    assert "keeping 32" in err
    with np.load(tmp_path / "m.npz") as data:
        assert data["shapedirs"].shape == (16 * 24, 3, 32) and data["image_size"].tolist() == [16, 24]
    code, _, err = run(["model", "info", str(tmp_path / "m.npz")], capsys)
    assert code == 2 and "is a texture model" in err and err.count("\n") == 1


def _other_size_model(files: Path, tmp: Path) -> Path:
    with np.load(files / "tex.npz") as data:
        arrays = {k: data[k] for k in data.files}
    flat = arrays["v_template"].reshape(SIZE, SIZE, 3)
    arrays["v_template"] = flat[::2, ::2].reshape(-1, 3)
    arrays["shapedirs"] = arrays["shapedirs"].reshape(SIZE, SIZE, 3, -1)[::2, ::2].reshape(-1, 3, 20)
    arrays["image_size"] = np.array([SIZE // 2, SIZE // 2])
    np.savez(tmp / "small.npz", **arrays)
    return tmp / "small.npz"


def _nan_exr(files: Path, tmp: Path) -> Path:
    image = read_image(files / "face.png")
    image[3, 4, 1] = np.nan
    write_image(tmp / "nan.exr", image)
    return tmp / "nan.exr"


def _bytes(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _png(path: Path, array: np.ndarray) -> Path:
    write_image(path, array)
    return path


def _inpaint(f: Path, *extra: str, image: str | None = None) -> list[str]:
    return ["inpaint", image or str(f / "face.png"), "--mask", str(f / "holes.png"), *extra]


BAD_INPAINT_INPUTS = {
    "mask of another size": lambda t, f: ["inpaint", str(f / "face.png"), "--mask",
                                          str(_png(t / "m.png", np.ones((SIZE, SIZE + 1, 1), np.float32)))],
    "all-black mask": lambda t, f: ["inpaint", str(f / "face.png"), "--mask",
                                    str(_png(t / "m.png", np.zeros((SIZE, SIZE, 1), np.float32)))],
    "model of another size": lambda t, f: _inpaint(f, "--model", str(_other_size_model(f, t))),
    "missing image": lambda t, f: _inpaint(f, image=str(t / "nope.png")),
    "corrupt image": lambda t, f: _inpaint(f, image=str(corrupt(t / "bad.png"))),
    "empty image": lambda t, f: _inpaint(f, image=str(_bytes(t / "e.png", b""))),
    "corrupt EXR": lambda t, f: _inpaint(f, image=str(_bytes(t / "b.exr", b"\x76\x2f\x31\x01junk"))),
    "NaN in an EXR": lambda t, f: _inpaint(f, image=str(_nan_exr(f, t))),
    "missing mask": lambda t, f: ["inpaint", str(f / "face.png"), "--mask", str(t / "nope.png")],
    "corrupt mask": lambda t, f: ["inpaint", str(f / "face.png"), "--mask", str(corrupt(t / "m.png"))],
    "missing model": lambda t, f: _inpaint(f, "--model", str(t / "nope.npz")),
    "corrupt model": lambda t, f: _inpaint(f, "--model", str(corrupt(t / "m.npz"))),
    "mesh model": lambda t, f: _inpaint(f, "--model", str(Path(__file__).resolve().parents[1] / "data_templates"
                                                          / "default_head.npz")),
    "grey image for an RGB model": lambda t, f: _inpaint(f, "--model", str(f / "tex.npz"), image=str(
        _png(t / "g.png", read_image(f / "face.png")[..., :1]))),
    "method needs a model": lambda t, f: _inpaint(f, "--method", "statistical"),
    "unknown method": lambda t, f: _inpaint(f, "--method", "magic"),
    "charts of another size": lambda t, f: _inpaint(f, "--charts",
                                                    str(_png(t / "c.png", np.ones((8, 8, 3), np.float32)))),
    "unwritable out": lambda t, f: _inpaint(f, "--out", "/proc/forbidden/fit.png"),
    "unwritable preview": lambda t, f: _inpaint(f, "--preview", "/proc/forbidden/fit.png"),
    "unsupported out format": lambda t, f: _inpaint(f, "--out", str(t / "fit.bmp")),
    "negative lambda": lambda t, f: _inpaint(f, "--lam", "-1"),
    "unknown start": lambda t, f: _inpaint(f, "--model", str(f / "tex.npz"), "--start", "zero"),
    "build from a missing folder": lambda t, f: ["model", "build-texture", str(t / "none" / "*.png"), "-o",
                                                 str(t / "fit.npz")],
    "build from one image": lambda t, f: ["model", "build-texture", str(f / "face.png"), "-o", str(t / "fit.npz")],
    "build with a bad size": lambda t, f: ["model", "build-texture", str(f / "train"), "-o", str(t / "fit.npz"),
                                           "--size", "32x"],
    "build from a corrupt image": lambda t, f: ["model", "build-texture", str(f / "face.png"),
                                                str(corrupt(t / "x.png")), "-o", str(t / "fit.npz")],
    "build into a missing folder": lambda t, f: ["model", "build-texture", str(f / "train"), "-o",
                                                 str(t / "no" / "fit.npz")],
}


@pytest.mark.parametrize("case", sorted(BAD_INPAINT_INPUTS))
def test_bad_inpaint_input_gives_one_line_and_exit_2(case, files, tmp_path, capsys):
    before = {p: p.read_bytes() for p in files.rglob("*") if p.is_file()}
    argv = BAD_INPAINT_INPUTS[case](tmp_path, files)
    if argv[0] == "inpaint":
        argv += ["--log", str(tmp_path / "fit.jsonl"), *FAST]
        argv += ["--out", str(tmp_path / "fit.png")] * ("--out" not in argv)
    code, _, err = run(argv, capsys)
    assert code == 2, err
    assert err.startswith("statfit: error: ") and err.count("\n") == 1, err
    assert {p: p.read_bytes() for p in files.rglob("*") if p.is_file()} == before
    assert not [p for p in tmp_path.rglob("*") if p.name.startswith("fit") or p.suffix == ".tmp"]
    if case == "model of another size":
        assert "--resize" in err


def test_resize_fits_a_model_of_another_size(files, tmp_path, capsys):
    out = tmp_path / "filled.png"
    code, _, err = run(_inpaint(files, "--model", str(_other_size_model(files, tmp_path)), "--resize", "--out",
                                str(out), *FAST), capsys)
    assert code == 0, err
    assert read_image(out).shape == (SIZE, SIZE, 3)


def test_inpaint_help_teaches(capsys):
    code, out, _ = run(["inpaint", "--help"], capsys)
    assert code == 0 and "--mask-invert" in out and "--resize" in out and "hybrid" in out
    code, out, _ = run(["model", "build-texture", "--help"], capsys)
    assert code == 0 and "--jitter" in out


def test_build_texture_defaults_to_the_images_own_size(tmp_path, capsys):
    """32 × 32 images give a 32 × 32 model, which inpaints a 32 × 32 image as it is (issue 17, #14)."""
    from statfit.io.image import write_image

    rng = np.random.default_rng(5)
    for i in range(4):
        write_image(tmp_path / f"t{i}.png", rng.random((32, 32, 3)).astype(np.float32))
    mask = np.ones((32, 32, 1), np.float32)
    mask[4:12, 4:12] = 0
    write_image(tmp_path / "mask.png", mask)
    code, _, err = run(["model", "build-texture", str(tmp_path / "t*.png"), "-o", str(tmp_path / "m.npz"),
                        "--k", "2", "-q"], capsys)
    assert code == 0, err
    with np.load(tmp_path / "m.npz") as data:
        assert data["image_size"].tolist() == [32, 32]
    code, _, err = run(["inpaint", str(tmp_path / "t0.png"), "--mask", str(tmp_path / "mask.png"), "--model",
                        str(tmp_path / "m.npz"), "--out", str(tmp_path / "o.png"), "--iterations", "5", "-q"], capsys)
    assert code == 0, err
