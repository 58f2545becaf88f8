"""``statfit batch report``: a real batch (two scans and a corrupt file) reported as a CSV checked
against an independent distance (libigl's exact point-to-mesh), and as a page opened in a headless
Chromium (every row there, every thumbnail decoded, sorting from the address); a render batch's
angular error; unreadable outputs as reasons; bad folders refused in one line."""
from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import igl
import numpy as np
import pytest

from conftest import run_cli
from statfit.batch.manifest import MANIFEST_NAME, read_rows
from statfit.batch.report import ReportRow, mark_outliers, ordered
from statfit.batch.report_page import MARK_IMAGES_JS
from statfit.io.mesh import read_mesh, read_points


@pytest.fixture(scope="session")
def chromium() -> str:
    """Chromium from Debian's packages, installed when missing (as root with apt-get, as in CI)."""
    found = shutil.which("chromium")
    if found is None:
        if shutil.which("apt-get") is None:
            pytest.skip("Chromium is not installed and there is no apt-get to install it")
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        for command in (["apt-get", "update"], ["apt-get", "install", "-y", "chromium"]):
            done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=1200)
            if done.returncode != 0:
                last = (done.stderr.strip().splitlines() or ["no message"])[-1]
                pytest.skip(f"Chromium could not be installed (`{' '.join(command)}`: {last})")
        found = shutil.which("chromium")
        if found is None:
            pytest.skip("apt-get installed chromium but no `chromium` is on PATH")
    return found


def dump_dom(chromium: str, url: str) -> str:
    """The page's DOM after its scripts ran, as headless Chromium serialises it."""
    done = subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=5000",
                           "--dump-dom", url], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


class Rows(HTMLParser):
    """The table rows (data-input, data-status, text) and every <img>'s attributes of a page."""

    def __init__(self, page: str):
        super().__init__()
        self.rows: list[dict[str, str]] = []
        self.images: list[dict[str, str]] = []
        self.feed(page)

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        attributes = {name: value or "" for name, value in attrs}
        if tag == "tr" and "data-input" in attributes:
            self.rows.append({**attributes, "text": ""})
        elif tag == "img":
            self.images.append(attributes)

    def handle_data(self, data: str) -> None:
        if self.rows:
            self.rows[-1]["text"] += data


@pytest.fixture(scope="module")
def fits(tmp_path_factory) -> Path:
    """A register batch of two small synthetic scans and a file of garbage bytes, reported."""
    root = tmp_path_factory.mktemp("report")
    scans = root / "scans"
    scans.mkdir()
    for seed in (1, 2):
        assert run_cli(["synth", "scan", "--seed", str(seed), "--points", "1500", "--out",
                        str(scans / f"scan{seed}.ply")])[0] == 0
    (scans / "garbage.ply").write_bytes(np.random.default_rng(0).bytes(300))
    code, err = run_cli(["batch", "register", str(scans / "*.ply"), "--out-dir", str(root / "fits"), "--workers", "1",
                         "--iterations", "60", "-q"])
    assert code == 1, err  # the garbage fails
    code, err = run_cli(["batch", "report", str(root / "fits")])
    assert code == 0, err
    return root / "fits"


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def test_the_csv_has_every_input_failures_first_and_errors_as_measured_independently(fits):
    rows = read_csv(fits / "report.csv")
    fitted = {row["input"]: row for row in read_rows(fits / MANIFEST_NAME) if row["event"] == "fit"}
    assert sorted(Path(row["input"]).name for row in rows) == ["garbage.ply", "scan1.ply", "scan2.ply"]
    assert Path(rows[0]["input"]).name == "garbage.ply" and rows[0]["status"] == "failed"
    assert rows[0]["reason"] == fitted[rows[0]["input"]]["error"] and "not a valid mesh" in rows[0]["reason"]
    assert rows[0]["error_mean"] == "" and rows[0]["outlier"] == "0"
    for row in rows[1:]:
        assert row["status"] == "done" and row["reason"] == "" and row["error_unit"] == "scan units"
        pose = fitted[row["input"]]["summary"]["pose"]
        assert row["pose_ambiguous"] == str(int(pose["ambiguous"]))
        assert float(row["pose_runner_up"]) == pytest.approx(pose["runner_up"], rel=1e-5)
        assert float(row["seconds"]) == pytest.approx(fitted[row["input"]]["seconds"], rel=1e-3)
    row = rows[1]
    vertices, faces = read_mesh(fits / row["output"])
    squared, _, _ = igl.point_mesh_squared_distance(read_points(row["input"]), vertices, faces)
    distance = np.sqrt(squared)
    assert float(row["error_mean"]) == pytest.approx(distance.mean(), rel=1e-4)
    assert float(row["error_median"]) == pytest.approx(np.median(distance), rel=1e-4)


def test_the_page_opens_in_chromium_with_every_row_and_every_thumbnail(fits, chromium):
    page = (fits / "report.html").read_text()
    assert "data:image/png;base64," in page
    assert not [link for link in Rows(page).images if not link["src"].startswith("data:")]
    assert "http://" not in page and "https://" not in page  # nothing fetched
    inputs = {row["input"]: row for row in read_csv(fits / "report.csv")}
    dom = Rows(dump_dom(chromium, (fits / "report.html").as_uri() + "#sort=-seconds"))
    assert sorted(row["data-input"] for row in dom.rows) == sorted(inputs)
    assert len(dom.images) == 2 and all(image.get("data-loaded") == "1" for image in dom.images), dom.images
    garbage = next(row for row in dom.rows if row["data-input"].endswith("garbage.ply"))
    assert garbage["data-status"] == "failed" and inputs[garbage["data-input"]]["reason"] in garbage["text"]
    by_seconds = sorted(inputs, key=lambda source: -float(inputs[source]["seconds"]))
    assert [row["data-input"] for row in dom.rows] == by_seconds  # #sort=-seconds sorted the table


def test_the_image_check_sees_an_image_that_does_not_load(tmp_path, chromium):
    page = tmp_path / "broken.html"
    page.write_text(f'<img src="data:image/png;base64,bm90IGEgcG5n"><script>{MARK_IMAGES_JS}</script>')
    assert [image.get("data-loaded") for image in Rows(dump_dom(chromium, page.as_uri())).images] == ["0"]


def test_failures_then_unreadable_then_outliers_come_first():
    errors = {"a": 1.0, "b": 1.1, "c": 9.0, "d": 0.9, "e": 1.05, "f": 20.0}
    rows = [ReportRow(name, status="done", error_mean=error) for name, error in errors.items()]
    rows += [ReportRow("pending"), ReportRow("failed", status="failed", reason="bad"),
             ReportRow("gone", status="done", reason="cannot check: output: not found")]
    mark_outliers(rows)
    assert [row.input for row in rows if row.outlier] == ["c", "f"]  # median 1.075, MAD 0.125: above 1.45
    assert [row.input for row in ordered(rows)] == ["failed", "gone", "f", "c", "pending", "a", "b", "d", "e"]


def test_a_missing_or_corrupt_output_is_its_rows_reason(fits, tmp_path):
    copy = tmp_path / "fits"
    shutil.copytree(fits, copy)
    (copy / "scan1.ply").unlink()
    (copy / "scan2.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    code, err = run_cli(["batch", "report", str(copy), "--out", str(tmp_path / "r.html"), "--csv",
                         str(tmp_path / "r.csv")])
    assert code == 0, err
    reasons = {Path(row["input"]).name: row["reason"] for row in read_csv(tmp_path / "r.csv")}
    assert reasons["scan1.ply"].startswith("cannot check: output:") and "not found" in reasons["scan1.ply"]
    assert reasons["scan2.ply"].startswith("cannot check: output:")
    assert (tmp_path / "r.html").is_file()


def test_a_render_batchs_error_is_the_angle_to_the_maps_normals(tmp_path):
    """A render batch whose output is the map's ground truth: the error is the raster's, well under a degree."""
    source, truth = tmp_path / "map.exr", tmp_path / "out" / "map.ply"
    truth.parent.mkdir()
    argv = ["synth", "normals", "--seed", "4", "--size", "96", "--out", str(source), "--gt", str(truth)]
    assert run_cli(argv)[0] == 0
    run = {"event": "run", "key": "k", "settings": {"command": "render", "model": None, "k": None,
                                                    "options": {"normal_space": "world"}}, "inputs": [str(source)]}
    fit = {"event": "fit", "input": str(source), "key": "k", "status": "done", "output": "map.ply", "seconds": 1.0,
           "summary": {}}
    (truth.parent / MANIFEST_NAME).write_text(json.dumps(run) + "\n" + json.dumps(fit) + "\n")
    assert run_cli(["batch", "report", str(truth.parent), "-q"])[0] == 0
    [row] = read_csv(truth.parent / "report.csv")
    assert row["status"] == "done" and row["reason"] == "" and row["error_unit"] == "degrees"
    assert 0 <= float(row["error_median"]) <= float(row["error_mean"]) < 0.5


def test_landmark_error_when_the_fits_used_landmarks(tmp_path, embedded_model):
    """A register row whose output is its own scan (error 0) and whose landmarks lie 1 mm off the fit's."""
    out = tmp_path / "out"
    out.mkdir()
    assert run_cli(["model", "sample", "--seed", "2", "-o", str(out / "face.ply")])[0] == 0
    shutil.copy(out / "face.ply", tmp_path / "face.ply")
    vertices, _ = read_mesh(out / "face.ply")
    landmarks = vertices[embedded_model.landmarks] + np.array([0.0, 0.0, 1e-3])
    landmarks[0] = np.nan  # a missing landmark is left out
    np.savetxt(tmp_path / "face.txt", landmarks)
    run = {"event": "run", "key": "k", "inputs": [str(tmp_path / "face.ply")],
           "settings": {"command": "register", "model": None, "k": None,
                        "options": {"landmarks": str(tmp_path / "face.txt")}}}
    fit = {"event": "fit", "input": str(tmp_path / "face.ply"), "key": "k", "status": "done", "output": "face.ply",
           "seconds": 1.0, "summary": {"model_to_scan": np.eye(4).tolist()}}
    (out / MANIFEST_NAME).write_text(json.dumps(run) + "\n" + json.dumps(fit) + "\n")
    assert run_cli(["batch", "report", str(out), "-q"])[0] == 0
    [row] = read_csv(out / "report.csv")
    assert row["reason"] == "" and float(row["error_mean"]) < 1e-9
    assert float(row["landmark_error"]) == pytest.approx(1e-3, rel=1e-4)


@pytest.mark.parametrize("what", ["no manifest", "missing", "a file"])
def test_a_folder_without_a_batch_is_refused_in_one_line_and_nothing_written(tmp_path, what):
    folder = {"no manifest": tmp_path, "missing": tmp_path / "nowhere", "a file": tmp_path / "x.ply"}[what]
    if what == "a file":
        folder.write_bytes(b"ply\n")
    before = sorted(tmp_path.rglob("*"))
    code, err = run_cli(["batch", "report", str(folder)])
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert sorted(tmp_path.rglob("*")) == before
