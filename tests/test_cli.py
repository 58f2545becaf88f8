"""The command line: jobs end to end on the embedded model, and bad input → one line, exit 2."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from statfit_cli.main import main

FAST = ["--iterations", "60", "-q"]


def run(argv: list[str], capsys) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    out, err = capsys.readouterr()
    return exit_info.value.code, out, err


def test_synth_register_eval(scan_files, tmp_path, capsys):
    scan, gt = scan_files
    fit, log = tmp_path / "fit.ply", tmp_path / "fit.jsonl"
    code, out, _ = run(["register", str(scan), "--method", "statistical", "--out", str(fit), "--log", str(log),
                        "--json", *FAST], capsys)
    assert code == 0
    summary = json.loads(out)
    assert summary["iterations"] == 60 and summary["output"] == str(fit)
    assert summary["threads"] == 1   # a small model runs on one thread, whatever the machine
    lines = [json.loads(line) for line in log.read_text().splitlines()]
    assert [lines[0]["type"], lines[-1]["type"]] == ["header", "summary"]
    assert {"iteration", "data", "elapsed"} <= set(lines[1]) and lines[0]["versions"]["torch"]
    mesh = trimesh.load(fit, process=False)
    template = trimesh.load(gt, process=False)
    np.testing.assert_array_equal(mesh.faces, template.faces)
    code, out, _ = run(["eval", str(fit), str(gt), "--scan", str(scan), "--json"], capsys)
    report = json.loads(out)
    assert code == 0 and report["observed"]["count"] + report["unobserved"]["count"] == len(mesh.vertices)


def test_same_seed_same_mesh_and_obj_output(scan_files, tmp_path, capsys):
    scan, _ = scan_files
    for name in ("a.ply", "b.ply", "c.obj"):
        assert run(["register", str(scan), "--out", str(tmp_path / name), *FAST], capsys)[0] == 0
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()
    a = trimesh.load(tmp_path / "a.ply", process=False)
    c = trimesh.load(tmp_path / "c.obj", process=False, maintain_order=True)
    np.testing.assert_allclose(a.vertices, c.vertices, atol=1e-6)
    np.testing.assert_array_equal(a.faces, c.faces)


def test_several_scans_are_sent_to_batch(scan_files, tmp_path, capsys):
    scan, _ = scan_files
    code, _, err = run(["register", str(scan), str(scan), "--out", str(tmp_path / "x.ply"), *FAST], capsys)
    assert code == 2 and "statfit batch register" in err and not (tmp_path / "x.ply").exists()


def test_stdin_to_stdout(scan_files, tmp_path):
    scan, _ = scan_files
    result = subprocess.run([sys.executable, "-m", "statfit_cli.main", "register", "-", "--out", "-", *FAST],
                            input=scan.read_bytes(), capture_output=True, check=True)
    (tmp_path / "fit.ply").write_bytes(result.stdout)
    assert len(trimesh.load(tmp_path / "fit.ply", process=False).vertices) > 1000


def test_millimetres_and_metres_give_the_same_relative_error(scan_files, tmp_path, capsys):
    """The embedded model is in metres; the same model and scan scaled to millimetres must fit the same:
    to rounding without the pose search (the maths has no units), and within 2% with it, where the
    trimmed subsets of its polish can differ by a point under other rounding (1.1% with numpy 1.26
    and scipy 1.11, pyproject's oldest; 0.02% with numpy 2.4)."""
    scan, gt = scan_files
    with np.load(Path(__file__).resolve().parents[1] / "data_templates" / "default_head.npz") as data:
        arrays = {k: data[k] for k in data.files}
    np.savez(tmp_path / "m.npz", **{k: v for k, v in arrays.items() if k in ("v_template", "faces", "shapedirs")})
    arrays["v_template"] = arrays["v_template"] * 1000
    arrays["shapedirs"] = arrays["shapedirs"] * 1000
    np.savez(tmp_path / "mm.npz", **{k: v for k, v in arrays.items() if k in ("v_template", "faces", "shapedirs")})
    points = trimesh.load(scan).vertices
    trimesh.PointCloud(points * 1000).export(tmp_path / "scan_mm.ply")
    gt_mesh = trimesh.load(gt, process=False)
    trimesh.Trimesh(gt_mesh.vertices * 1000, gt_mesh.faces, process=False).export(tmp_path / "gt_mm.ply")
    errors = {}
    inputs = (("m.npz", scan, gt), ("mm.npz", tmp_path / "scan_mm.ply", tmp_path / "gt_mm.ply"))
    for align in ("none", "auto"):
        for model, points_file, truth in inputs:
            fit = tmp_path / f"fit_{align}_{model}.ply"
            assert run(["register", str(points_file), "--model", str(tmp_path / model), "--out", str(fit),
                        "--method", "statistical", "--align", align, *FAST], capsys)[0] == 0
            evaluated = json.loads(run(["eval", str(fit), str(truth), "--json"], capsys)[1])
            errors[align, model] = evaluated["all"]["mean_rel"]
    assert errors["none", "mm.npz"] == pytest.approx(errors["none", "m.npz"], rel=1e-4), errors
    assert errors["auto", "mm.npz"] == pytest.approx(errors["auto", "m.npz"], rel=0.02), errors


def corrupt(path: Path) -> Path:
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\nend_header\n\x00\x01")
    return path


def nan_scan(path: Path) -> Path:
    points = np.random.default_rng(0).normal(size=(100, 3)) * 0.05
    points[5] = np.nan
    path.write_text("ply\nformat ascii 1.0\nelement vertex 100\nproperty float x\nproperty float y\n"
                    "property float z\nend_header\n" + "\n".join(" ".join(map(str, p)) for p in points) + "\n")
    return path


def empty_scan(path: Path) -> Path:
    path.write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
                    "property float z\nend_header\n")
    return path


def far_units(scan: Path, path: Path) -> Path:
    trimesh.PointCloud(trimesh.load(scan).vertices * 1000).export(path)
    return path


def bad_model(path: Path) -> Path:
    np.savez(path, v_template=np.zeros((10, 3)), faces=np.array([[0, 1, 2]]))
    return path


BAD_INPUTS = {
    "missing scan": lambda t, s: ["register", str(t / "nope.ply")],
    "corrupt scan": lambda t, s: ["register", str(corrupt(t / "bad.ply"))],
    "empty file": lambda t, s: ["register", str((t / "zero.ply").write_bytes(b"") and t / "zero.ply")],
    "scan without points": lambda t, s: ["register", str(empty_scan(t / "empty.ply"))],
    "NaN coordinates": lambda t, s: ["register", str(nan_scan(t / "nan.ply"))],
    "unknown method": lambda t, s: ["register", str(s), "--method", "magic"],
    "unknown alignment": lambda t, s: ["register", str(s), "--align", "sideways"],
    "model missing keys": lambda t, s: ["register", str(s), "--model", str(bad_model(t / "m.npz"))],
    "missing model": lambda t, s: ["register", str(s), "--model", str(t / "none.npz")],
    "unwritable output": lambda t, s: ["register", str(s), "--out", "/proc/forbidden/fit.ply"],
    "missing output folder": lambda t, s: ["register", str(s), "--out", str(t / "no" / "fit.ply")],
    "unit mismatch": lambda t, s: ["register", str(far_units(s, t / "mm.ply")), "--align", "none"],
    "unknown option": lambda t, s: ["register", str(s), "--frobnicate"],
    "unknown clutter rule": lambda t, s: ["register", str(s), "--clutter", "sometimes", "--out", str(t / "fit.ply")],
    "realistic scan in unknown units": lambda t, s: ["synth", "scan", "--realistic", "--units", "km", "--out",
                                                     str(t / "fit_scan.ply")],
    "realistic scan with loose outliers": lambda t, s: ["synth", "scan", "--realistic", "--outliers", "0.1", "--out",
                                                        str(t / "fit_scan.ply")],
    "landmarks out without --realistic": lambda t, s: ["synth", "scan", "--landmarks-out", str(t / "fit_lm.txt"),
                                                       "--out", str(t / "fit_scan.ply")],
    "eval of different topologies": lambda t, s: ["eval", str(s), str(s)],
    "bad k": lambda t, s: ["register", str(s), "--k", "0"],
    "eval of a missing fit": lambda t, s: ["eval", str(t / "nope.ply"), str(s)],
    "eval of a corrupt fit": lambda t, s: ["eval", str(corrupt(t / "bad.ply")), str(s)],
    "eval of an empty fit": lambda t, s: ["eval", str((t / "zero.ply").write_bytes(b"") and t / "zero.ply"), str(s)],
    "model info of a missing model": lambda t, s: ["model", "info", str(t / "none.npz")],
    "model info of a corrupt model": lambda t, s: ["model", "info", str(corrupt(t / "m.npz"))],
    "synth with a missing delta file": lambda t, s: ["synth", "scan", "--out", str(t / "fit.ply"), "--delta",
                                                     str(t / "none.npz"), "--delta-name", "jawOpen"],
    "synth into a missing folder": lambda t, s: ["synth", "scan", "--out", str(t / "no" / "fit.ply")],
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_input_gives_one_line_and_exit_2(case, scan_files, tmp_path, capsys):
    scan, _ = scan_files
    before = scan.read_bytes()
    argv = BAD_INPUTS[case](tmp_path, scan)
    code, out, err = run(argv + ["-q"] * (argv[0] == "register"), capsys)
    assert code == 2, err
    assert err.startswith("statfit: error: ") and err.count("\n") == 1, err
    assert scan.read_bytes() == before
    assert not [p for p in tmp_path.rglob("*") if p.suffix in (".tmp",) or p.name.startswith("fit")]


def test_bad_input_from_a_real_process_has_no_traceback(tmp_path):
    result = subprocess.run([sys.executable, "-m", "statfit_cli.main", "register", str(corrupt(tmp_path / "x.ply"))],
                            capture_output=True, text=True)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.count("\n") == 1


def test_far_scan_warns_but_fits(scan_files, tmp_path, capsys):
    scan, _ = scan_files
    shifted = tmp_path / "shifted.ply"
    trimesh.PointCloud(trimesh.load(scan).vertices + [0.1, 0.0, 0.0]).export(shifted)
    code, _, err = run(["register", str(shifted), "--out", str(tmp_path / "f.ply"), "--align", "none", *FAST], capsys)
    assert code == 0 and "statfit: warning: the scan is far from the model" in err


def test_divergence_is_reported_with_its_iteration(scan_files, tmp_path, capsys):
    scan, _ = scan_files
    code, _, err = run(["register", str(scan), "--method", "none", "--lr", "1e30", "--out",
                        str(tmp_path / "fit.ply"), *FAST], capsys)
    assert code == 2 and "diverged at iteration" in err
    assert not (tmp_path / "fit.ply").exists()


def test_help_teaches(capsys):
    code, out, _ = run(["register", "--help"], capsys)
    assert code == 0 and "statistical" in out and "--align" in out


def test_similarity_alignment_takes_a_scan_in_other_units(scan_files, tmp_path, capsys):
    scan, gt = scan_files
    millimetres = far_units(scan, tmp_path / "scan_mm.ply")
    code, out, _ = run(["register", str(millimetres), "--align", "similarity", "--out", str(tmp_path / "fit.ply"),
                        "--json", *FAST], capsys)
    assert code == 0
    scale = np.linalg.norm(np.array(json.loads(out)["model_to_scan"])[:3, 0])
    assert scale == pytest.approx(1000, rel=0.1)
    fit = trimesh.load(tmp_path / "fit.ply", process=False).vertices
    truth = trimesh.load(gt, process=False).vertices * 1000
    assert np.linalg.norm(fit - truth, axis=1).mean() < 0.15 * np.sqrt(((truth - truth.mean(0)) ** 2).sum(1).mean())


def test_outputs_honour_the_umask_and_long_names_fit(scan_files, tmp_path, capsys):
    """A fit written as a shell redirect would be: mode 0666 & ~umask; a 250-character name works."""
    import os

    scan, _ = scan_files
    out = tmp_path / ("f" * 246 + ".ply")
    previous = os.umask(0o022)
    try:
        code, _, err = run(["register", str(scan), "--out", str(out), "--log", str(tmp_path / "fit.jsonl"), *FAST],
                           capsys)
    finally:
        os.umask(previous)
    assert code == 0, err
    assert out.stat().st_mode & 0o777 == 0o644 and (tmp_path / "fit.jsonl").stat().st_mode & 0o777 == 0o644


def test_progress_lines_without_a_terminal(scan_files, tmp_path, capsys, monkeypatch):
    from statfit_cli import common

    monkeypatch.setattr(common, "PROGRESS_LINE_SECONDS", 0.0)
    scan, _ = scan_files
    code, _, err = run(["register", str(scan), "--out", str(tmp_path / "f.ply"), "--iterations", "30"], capsys)
    assert code == 0 and "statfit: scan.ply: iteration 11/30, loss" in err


def test_version(capsys):
    from statfit import __version__

    code, out, _ = run(["--version"], capsys)
    assert code == 0 and out.strip() == f"statfit {__version__}"


def test_help_and_refused_options_import_no_fitting_code():
    """`statfit --help`, every command's help and an option refused before any work answer without
    importing torch, trimesh or SciPy: 0.4 s instead of 3–4 s (docs/benchmarks.md §17). The commands
    import the library when they run."""
    import subprocess
    import sys

    code = ("import sys\nfrom statfit_cli.main import main\n"
            "for argv in (['--help'], ['register', '--help'], ['batch', 'render', '--help'], ['model', 'cut', '--help'],"
            " ['synth', 'scan', '--help'], ['splat', '--help'], ['register', 'scan.ply', '--trim', '2']):\n"
            "    try:\n        main(argv)\n    except SystemExit as done:\n"
            "        print(argv[0], done.code, file=sys.stderr)\n"
            "print(sorted(m for m in ('torch', 'trimesh', 'scipy', 'matplotlib') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip().splitlines()[-1] == "[]", (done.stdout[-500:], done.stderr[-2000:])
    assert done.stderr.count(" 0\n") == 6 and "--trim" in done.stderr and done.stderr.endswith("register 2\n"), done.stderr


def test_a_mistyped_path_is_refused_before_the_library_loads(tmp_path):
    """A missing input or an output folder that does not exist is the reader's own line, said before
    a command imports torch, trimesh or SciPy (~2 s): the paths are checked first."""
    import subprocess
    import sys

    (tmp_path / "scan.ply").write_text("ply")
    makehuman = "mh is not a folder (expected the MakeHuman data folder: 3dobjs/, targets/, mesh_metadata/)"
    cases = [("scan not found: nosuch.ply", ["register", "nosuch.ply"]),
             ("model file not found: nosuch.npz", ["register", "scan.ply", "--model", "nosuch.npz"]),
             ("landmark file not found: l.txt", ["register", "scan.ply", "--landmarks", "l.txt"]),
             ("output folder does not exist: nodir", ["register", "scan.ply", "--out", "nodir/fit.ply"]),
             ("normal map not found: n.exr", ["render", "n.exr"]),
             ("camera file not found: c.json", ["render", "scan.ply", "--camera", "c.json"]),
             ("views folder not found: views", ["splat", "views"]),
             ("mask not found: m.png", ["inpaint", "scan.ply", "--mask", "m.png"]),
             ("no file matches 'scans/*.ply'", ["batch", "register", "scans/*.ply", "--out-dir", "fits"]),
             ("camera file not found: cams.json", ["batch", "render", "scan.ply", "--camera", "cams.json", "--out-dir",
                                                   "fits"]),
             ("file not found: gt.ply", ["eval", "scan.ply", "gt.ply"]),
             ("model file not found: nosuch.npz", ["model", "info", "nosuch.npz"]),
             ("params file not found: p.json", ["model", "sample", "--params", "p.json", "-o", "s.ply"]),
             ("model file not found: nosuch.pkl", ["model", "import", "nosuch.pkl", "-o", "m.npz"]),
             ("mask file not found: masks.pkl", ["model", "import", "scan.ply", "-o", "m.npz", "--masks", "masks.pkl"]),
             ("file not found: b.ply", ["model", "build", "scan.ply", "b.ply", "-o", "m.npz"]),
             (makehuman, ["model", "build-makehuman", "mh", "-o", "m.npz"]),
             ("file not found: shape.ply", ["synth", "normals", "--shape", "shape.ply", "-o", "n.exr"]),
             (makehuman, ["synth", "body", "mh", "-o", "b.ply"]),
             ("delta file not found: d.npz", ["synth", "views", "--delta", "d.npz", "--delta-name", "jawOpen", "-o",
                                              "views"])]
    code = ("import sys\nfrom statfit_cli.main import main\n"
            f"for argv in {[argv for _, argv in cases]!r}:\n"
            "    try:\n        main(argv)\n    except SystemExit as done:\n"
            "        print(done.code, file=sys.stderr)\n"
            "print(sorted(m for m in ('torch', 'trimesh', 'scipy') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert done.returncode == 0 and done.stdout.strip() == "[]", (done.stdout[-500:], done.stderr[-2000:])
    lines = done.stderr.strip().splitlines()
    assert lines[1::2] == ["2"] * len(cases), done.stderr
    assert [line.removeprefix("statfit: error: ") for line in lines[::2]] == [line for line, _ in cases], done.stderr
    assert sorted(path.name for path in tmp_path.iterdir()) == ["scan.ply"]   # no output, no --out-dir made


def test_the_cli_starts_without_importing_matplotlib():
    """matplotlib (0.4 s of every process's start) is imported when a preview is drawn, not by the
    CLI's modules nor by `batch report`'s, which use the preview's pixel functions only."""
    import subprocess
    import sys

    code = ("import sys, statfit_cli.main, statfit.batch.report, statfit.render.preview, statfit.registration.preview; "
            "print('matplotlib' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "False", (done.stdout, done.stderr[-2000:])
