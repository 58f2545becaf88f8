"""Every numeric option of every command, driven with NaN, infinities, negative, huge and
non-numeric values: the command either runs (exit 0; a batch may record its input as failed, exit 1)
or refuses in one line on stderr with exit 2, writing nothing — never a traceback. The options are found by walking the CLI itself, so a new
option is fuzzed without touching this file."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import typer

from statfit.io.image import write_image
from conftest import run_cli
from statfit_cli.main import app
from statfit.model.statmodel import default_model_path

FLOATS = ["nan", "inf", "-1", "1e30", "x"]
INTS = ["-1", "999999999999999999999", "x", "2.5"]


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("fuzz-inputs")
    for argv in (["synth", "scan", "--out", str(folder / "scan.ply"), "--gt", str(folder / "gt.ply")],
                 ["synth", "normals", "--size", "48", "--out", str(folder / "n.exr"), "--camera-out",
                  str(folder / "cam.json")],
                 *(["model", "sample", "-o", str(folder / f"s{i}.ply"), "--seed", str(i)] for i in range(3)),
                 ["synth", "views", "--views", "3", "--size", "24", "--out", str(folder / "views")],
                 ["splat", str(folder / "views"), "--iterations", "2", "-q", "--out", str(folder / "sfit.ply"),
                  "--splats", str(folder / "splats.ply")]):
        assert run_cli(argv)[0] == 0, argv
    image = np.random.default_rng(0).random((24, 24, 3)).astype(np.float32)
    write_image(folder / "img.png", image)
    mask = np.ones((24, 24, 1), np.float32)
    mask[6:12, 6:12] = 0
    write_image(folder / "mask.png", mask)
    return folder


def base_argv(command: tuple[str, ...], inputs: Path, out: Path) -> list[str]:
    """A valid, quick invocation of ``command`` writing into ``out``."""
    i, o = inputs, out
    return {
        ("register",): ["register", str(i / "scan.ply"), "--iterations", "2", "-q", "--out", str(o / "fit.ply")],
        ("render",): ["render", str(i / "n.exr"), "--camera", str(i / "cam.json"), "--iterations", "2", "-q",
                      "--out", str(o / "fit.ply")],
        ("demo",): ["demo", "--iterations", "2", "-q"],
        ("eval",): ["eval", str(i / "gt.ply"), str(i / "gt.ply"), "--scan", str(i / "scan.ply")],
        ("inpaint",): ["inpaint", str(i / "img.png"), "--mask", str(i / "mask.png"), "--iterations", "2", "-q",
                       "--out", str(o / "o.png")],
        ("synth", "scan"): ["synth", "scan", "--points", "500", "--out", str(o / "s.ply")],
        ("synth", "normals"): ["synth", "normals", "--size", "32", "--out", str(o / "n.exr")],
        ("model", "import"): ["model", "import", str(i / "missing.npz"), "-o", str(o / "m.npz")],
        ("model", "build"): ["model", "build", *(str(i / f"s{k}.ply") for k in range(3)), "-o", str(o / "b.npz")],
        ("model", "sample"): ["model", "sample", "-o", str(o / "s.ply")],
        ("model", "info"): ["model", "info"],
        ("model", "cut"): ["model", "cut", str(default_model_path()), "--vertices", "2000", "-o", str(o / "c.npz")],
        ("batch", "register"): ["batch", "register", str(i / "scan.ply"), "--iterations", "2", "-q", "--workers", "1",
                                "--out-dir", str(o / "fits")],
        ("batch", "render"): ["batch", "render", str(i / "n.exr"), "--camera", str(i / "cam.json"), "--iterations", "2",
                              "-q", "--workers", "1", "--out-dir", str(o / "fits")],
        # a folder that is not MakeHuman's: an accepted number still ends in one line and exit 2, nothing built
        ("model", "build-makehuman"): ["model", "build-makehuman", str(i / "no-makehuman"), "-o", str(o / "b.npz")],
        ("synth", "body"): ["synth", "body", str(i / "no-makehuman"), "-o", str(o / "b.ply")],
        ("synth", "views"): ["synth", "views", "--views", "2", "--size", "24", "--out", str(o / "v")],
        ("splat",): ["splat", str(i / "views"), "--iterations", "2", "-q", "--out", str(o / "fit.ply")],
        ("splat-render",): ["splat-render", str(i / "splats.ply"), str(i / "sfit.ply"), "--camera",
                            str(i / "views" / "cameras.json"), "--view", "0", "--out", str(o / "r.png")],
        ("model", "build-texture"): ["model", "build-texture", str(i / "img.png"), str(i / "mask.png"), "-o",
                                     str(o / "t.npz"), "--k", "1", "--size", "24x24"],
    }[command]


def _number_kind(param) -> type | None:
    """int or float for a numeric option, else None. Typer versions differ: a click parameter type
    (``IntParamType``, ``FloatParamType`` or their ranges; click's own, or the copy of click that
    typer 0.2x vendors), or, in versions whose parameters carry no type, the annotation in
    ``type_descriptor``."""
    for cls in type(getattr(param, "type", None)).__mro__:
        if cls.__name__ in ("IntParamType", "FloatParamType"):
            return int if cls.__name__ == "IntParamType" else float
    kind = getattr(getattr(param, "type_descriptor", None), "annotation", None)
    return kind if kind in (int, float) else None


def numeric_options() -> list[tuple[tuple[str, ...], str, type]]:
    def walk(command, path=()):
        if hasattr(command, "commands"):
            for name, sub in command.commands.items():
                yield from walk(sub, (*path, name))
        else:
            for param in command.params:
                if getattr(param, "param_type_name", None) == "option" and param.opts:
                    kind = _number_kind(param)
                    if kind is not None:
                        yield path, param.opts[0], kind

    return list(walk(typer.main.get_command(app)))


OPTIONS = numeric_options()


def test_the_walk_finds_the_options():
    names = {(" ".join(c), o) for c, o, _ in OPTIONS}
    assert {("register", "--lr"), ("synth scan", "--points"), ("synth normals", "--size"),
            ("inpaint", "--beta"), ("model sample", "--sigma")} <= names


@pytest.mark.parametrize("command, option, kind", OPTIONS, ids=[f"{' '.join(c)} {o}" for c, o, _ in OPTIONS])
def test_bad_numbers_never_crash(command, option, kind, inputs, tmp_path):
    for value in FLOATS if kind is float else INTS:
        out = tmp_path / value
        out.mkdir()
        argv = base_argv(command, inputs, out)
        if option in argv:
            del argv[argv.index(option):argv.index(option) + 2]
        code, err = run_cli([*argv, option, value])
        allowed = (0, 1, 2) if command[0] == "batch" else (0, 2)  # batch: 1 = an input failed (e.g. diverged)
        assert code in allowed and "Traceback" not in err, (option, value, err[-500:])
        if code == 2:
            assert err.count("\n") == 1 and err.startswith("statfit: error:"), (option, value, err)
            assert not any(out.iterdir()), (option, value)
    shutil.rmtree(tmp_path, ignore_errors=True)
