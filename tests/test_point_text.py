"""Scans as text point clouds (``.xyz``, ``.asc``, ``.csv``, ``.txt``), as scanner software exports
them: read to the points that were written, fitted to the bytes of the same points in a PLY, and
anything else refused in one line."""
from __future__ import annotations

import json

import numpy as np
import pytest

from statfit.io.mesh import read_mesh, read_points
from test_cli import run

FAST = ["--iterations", "30"]


@pytest.fixture(scope="module")
def points(scan_files) -> np.ndarray:
    return read_points(scan_files[0])


def _write_layouts(folder, points: np.ndarray) -> dict[str, bytes]:
    """The same points in the layouts scanner software writes, each as its file's bytes."""
    rows = [[f"{value:.17g}" for value in row] for row in points]
    normals = np.random.default_rng(0).normal(size=points.shape)
    layouts = {
        "comments.xyz": "# exported by a scanner\n# X Y Z\n" + "".join(" ".join(r) + "\n" for r in rows),
        "header.csv": "X,Y,Z,Nx,Ny,Nz,Intensity\n" + "".join(",".join(r + [f"{n:.6f}" for n in normal] + ["7"]) + "\n"
                                                         for r, normal in zip(rows, normals)),
        "semicolons.asc": "// x;y;z\n" + "".join("; ".join(r) + "\n" for r in rows),
        "tabs.txt": "\n\n" + "".join("\t".join(r) + "   # a point\n" for r in rows),
    }
    encoded = {name: text.encode() for name, text in layouts.items()}
    encoded["bom.xyz"] = b"\xef\xbb\xbf" + encoded["comments.xyz"].split(b"\n", 2)[2]
    encoded["windows.xyz"] = encoded["comments.xyz"].replace(b"\n", b"\r\n")
    encoded["old_mac.xyz"] = encoded["comments.xyz"].replace(b"\n", b"\r")
    for name, data in encoded.items():
        (folder / name).write_bytes(data)
    return encoded


def test_text_clouds_read_as_the_points_written(points, tmp_path):
    for name in _write_layouts(tmp_path, points):
        np.testing.assert_array_equal(read_points(tmp_path / name), points, err_msg=name)


def test_a_text_cloud_fits_to_the_bytes_of_the_same_points_in_a_ply(scan_files, points, tmp_path, capsys):
    scan, gt = scan_files
    _write_layouts(tmp_path, points)
    code, _, err = run(["register", str(scan), "--out", str(tmp_path / "ply.ply"), *FAST], capsys)
    assert code == 0, err
    for name in ("comments.xyz", "header.csv"):
        code, _, err = run(["register", str(tmp_path / name), "--out", str(tmp_path / f"{name}.ply"), *FAST], capsys)
        assert code == 0, err
        assert (tmp_path / f"{name}.ply").read_bytes() == (tmp_path / "ply.ply").read_bytes(), name
    # `eval --scan` reads it too: the same report as with the PLY.
    reports = []
    for cloud in (scan, tmp_path / "semicolons.asc"):
        code, out, err = run(["eval", str(tmp_path / "ply.ply"), str(gt), "--scan", str(cloud), "--json"], capsys)
        assert code == 0, err
        reports.append(json.loads(out))
    assert reports[0] == reports[1]


@pytest.mark.parametrize("name, data, message", [
    ("short.xyz", b"1 2 3\n4 5\n6 7 8\n", "short.xyz: row 2 does not start with three numbers x y z: '4 5'"),
    ("words.xyz", b"1 2 3\n4 5 6\n# a comment\nfoo bar baz\n", "row 4 does not start with three numbers"),
    ("two_headers.xyz", b"X Y Z\nA B C\n1 2 3\n", "two_headers.xyz: row 2 is not a point (x y z): 'A B C'"),
    ("binary.xyz", bytes(range(256)) * 8, "binary.xyz is not text"),
    ("comments.xyz", b"# nothing but comments\n\n", "comments.xyz contains no points"),
    ("decimal_commas.csv", b"1,5;2,5;3,5\n", "no row starts with three numbers x y z (row 1: '1,5;2,5;3,5')"),
    ("nan.xyz", b"1 2 3\nnan 1 1\n" + b"1 1 1\n" * 20, "nan.xyz has NaN or infinite coordinates (1 point)"),
    ("few.xyz", b"1 2 3\n4 5 6\n", "has only 2 points; need at least 10"),
    ("unknown.pcd", b"1 2 3\n", "unsupported format '.pcd'; use one of .ply, .obj, .stl, .off, .xyz, .asc, .csv, .txt"),
])
def test_a_bad_text_cloud_is_refused_in_one_line(tmp_path, capsys, name, data, message):
    (tmp_path / name).write_bytes(data)
    out = tmp_path / "fit.ply"
    code, _, err = run(["register", str(tmp_path / name), "--out", str(out), *FAST], capsys)
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_synth_writes_a_scan_in_the_format_its_name_asks_for(tmp_path, capsys):
    """A point-cloud scan as text reads back to the PLY's points; a realistic scan (a mesh) as OBJ
    to the PLY's mesh; a suffix of the other kind is refused before any work."""
    names = ("scan.ply", "scan.xyz", "scan.csv", "real.ply", "real.obj")
    for name in names:
        realistic = ["--realistic"] if name.startswith("real") else []
        code, _, err = run(["synth", "scan", "--seed", "3", *realistic, "--out", str(tmp_path / name)], capsys)
        assert code == 0, err
    ply = read_points(tmp_path / "scan.ply")
    for name in ("scan.xyz", "scan.csv"):
        np.testing.assert_array_equal(read_points(tmp_path / name), ply, err_msg=name)
    assert (tmp_path / "scan.csv").read_text().startswith("x,y,z\n")
    (vertices, faces), (obj_vertices, obj_faces) = (read_mesh(tmp_path / name) for name in ("real.ply", "real.obj"))
    np.testing.assert_array_equal(obj_faces, faces)
    np.testing.assert_allclose(obj_vertices, vertices, atol=1e-6 * np.abs(vertices).max())
    for arguments, message in ((["--out", "x.obj"], "x.obj: point clouds are written as .ply or as text"),
                               (["--realistic", "--out", "x.xyz"], "x.xyz: meshes are written as .ply or .obj")):
        code, _, err = run(["synth", "scan", *[str(tmp_path / a) if a.startswith("x.") else a for a in arguments]],
                           capsys)
        assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert sorted(path.name for path in tmp_path.iterdir()) == sorted(names)
