"""Batches: outputs mirrored and refused on clashes, the manifest's skip rule, failures isolated
(bad inputs, crashing and hanging workers), kill and resume, the Dask engine, and the same meshes
as one-by-one ``statfit register``."""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from batch_stubs import copy_or_misbehave, copy_or_misbehave_together
from conftest import run_cli
from statfit.batch.engines import LocalPool
from statfit.batch.fits import FitJob
from statfit.batch.manifest import MANIFEST_NAME, Manifest, batch_status, read_rows
from statfit.batch.plan import expand_inputs, plan_outputs
from statfit.batch.run import WORKER_DIED, run_batch
from statfit.errors import StatfitError
from statfit.io.mesh import points_bytes
from statfit.core.methods import resolve
from statfit.synth.sample import sample_target, scan_from_view

FAST = ["--iterations", "60", "--align", "none"]   # the scans lie in the model's frame: no pose search


@pytest.fixture(scope="module")
def scans(tmp_path_factory, embedded_model) -> Path:
    """12 small scans of the embedded model in two sub-folders, 2 of them corrupt."""
    root = tmp_path_factory.mktemp("scans")
    for index in range(10):
        rng = np.random.default_rng(index)
        target = sample_target(embedded_model, rng)
        points = scan_from_view(target, embedded_model.faces, rng, num_points=1500)
        folder = root / ("left" if index % 2 else "right")
        folder.mkdir(exist_ok=True)
        (folder / f"scan{index:02d}.ply").write_bytes(points_bytes(points))
    (root / "left" / "broken.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 5\nend_header\n1 2\n")
    (root / "right" / "empty.ply").write_bytes(b"")
    return root


def fit_rows(out_dir: Path) -> list[dict]:
    return [row for row in read_rows(out_dir / MANIFEST_NAME) if row["event"] == "fit"]


def test_outputs_mirror_sub_folders_and_clashes_are_refused(tmp_path):
    for name in ("a/x.ply", "a/y.obj", "b/x.ply"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_text("")
    items = plan_outputs(expand_inputs([str(tmp_path / "**" / "*.*")]), tmp_path / "out")
    assert sorted(str(i.output.relative_to(tmp_path / "out")) for i in items) == ["a/x.ply", "a/y.ply", "b/x.ply"]
    (tmp_path / "a" / "x.obj").write_text("")
    with pytest.raises(StatfitError, match="would both be written"):
        plan_outputs(expand_inputs([str(tmp_path / "a" / "*")]), tmp_path / "out")
    with pytest.raises(StatfitError, match="no file matches"):
        expand_inputs([str(tmp_path / "*.stl")])
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "old.ply").write_text("")  # an earlier batch's output is never an input
    found = expand_inputs([str(tmp_path / "**" / "*.ply")], exclude=tmp_path / "out")
    assert tmp_path / "out" / "old.ply" not in found and len(found) == 2


def test_manifest_skips_a_line_cut_short_and_refuses_a_second_writer(tmp_path):
    path = tmp_path / MANIFEST_NAME
    with Manifest(path) as manifest:
        manifest.append({"event": "fit", "input": "a", "status": "done"})
        with pytest.raises(StatfitError, match="another batch"):
            Manifest(path)
    with open(path, "ab") as handle:
        handle.write(b'{"event": "fit", "input": "b", "sta')  # killed mid-line
    with Manifest(path) as manifest:
        manifest.append({"event": "fit", "input": "c", "status": "done"})
    assert [row["input"] for row in read_rows(path)] == ["a", "c"]


def test_crashing_and_hanging_fits_fail_alone_and_the_batch_goes_on(tmp_path):
    names = ["ok1", "crash", "ok2", "hang", "bad", "ok3", "ok4"]
    for name in names:
        (tmp_path / f"{name}.ply").write_bytes(name.encode())
    items = plan_outputs(expand_inputs([str(tmp_path / "*.ply")]), tmp_path / "out")
    (tmp_path / "out").mkdir()
    job = FitJob("register", None, None, resolve("none"))
    engine = LocalPool(2)
    try:
        report = run_batch(items, job, tmp_path / "out", engine, timeout=8, work=copy_or_misbehave)
    finally:
        engine.close()
    failed = dict((Path(source).stem, reason) for source, reason in report.failed)
    assert failed == {"crash": WORKER_DIED, "hang": "timed out after 8 s", "bad": "bad is bad"}
    assert report.done == 4
    for name in ("ok1", "ok2", "ok3", "ok4"):
        assert (tmp_path / "out" / f"{name}.ply").read_bytes() == name.encode()
    assert not (tmp_path / "out" / "crash.ply").exists()


def test_a_group_that_crashes_or_hangs_is_rerun_an_input_at_a_time(tmp_path):
    names = ["ok1", "crash", "ok2", "hang", "bad", "ok3", "ok4", "ok5"]
    for name in names:
        (tmp_path / f"{name}.ply").write_bytes(name.encode())
    items = plan_outputs(expand_inputs([str(tmp_path / "*.ply")]), tmp_path / "out")
    (tmp_path / "out").mkdir()
    job = FitJob("register", None, None, resolve("none"), together=3)
    engine = LocalPool(2)
    try:
        report = run_batch(items, job, tmp_path / "out", engine, timeout=4, work=copy_or_misbehave,
                           group_work=copy_or_misbehave_together)
    finally:
        engine.close()
    failed = dict((Path(source).stem, reason) for source, reason in report.failed)
    assert failed == {"crash": WORKER_DIED, "hang": "timed out after 4 s", "bad": "bad is bad"}
    assert report.done == 5
    for name in ("ok1", "ok2", "ok3", "ok4", "ok5"):
        assert (tmp_path / "out" / f"{name}.ply").read_bytes() == name.encode()


def test_groups_are_split_so_that_no_worker_idles(tmp_path):
    for index in range(10):
        (tmp_path / f"ok{index}.ply").write_bytes(b"ok")
    items = plan_outputs(expand_inputs([str(tmp_path / "*.ply")]), tmp_path / "out")
    (tmp_path / "out").mkdir()
    engine = LocalPool(2)
    try:
        run_batch(items, FitJob("register", None, None, resolve("none"), together=8), tmp_path / "out", engine,
                  work=copy_or_misbehave, group_work=copy_or_misbehave_together)
    finally:
        engine.close()
    assert sorted(row["summary"]["group"] for row in fit_rows(tmp_path / "out")) == [5] * 10   # not 8 + 2


def test_scans_registered_together_fit_as_one_by_one(scans, tmp_path):
    """``--together``: each worker registers 4 scans in one program (two corrupt ones fail alone);
    the fits are as close to their scans as the one-by-one fits, and the settings say how it was made.
    On average within 1.15×, each within 2×: a fit's last hundredths of a millimetre move by tens of
    per cent for any change of rounding (docs/studies.md §29). On an Intel Xeon (session 31) one scan's
    fit together was 1.42× its fit alone and another 0.85×, the mean 1.04×; on the AMD EPYC of
    earlier sessions each was within 1.25×."""
    import trimesh

    from statfit.geometry.metrics import inside_distance

    together, alone = tmp_path / "together", tmp_path / "alone"
    for out, extra in ((together, ["--together", "4"]), (alone, [])):   # each fit its own pose search, as shipped
        code, err = run_cli(["batch", "register", str(scans / "**" / "*.ply"), "--out-dir", str(out), "--workers",
                             "2", "--seed", "3", "-q", "--iterations", "60", *extra])
        assert code == 1, err
        rows = fit_rows(out)
        assert sorted(Path(r["input"]).name for r in rows if r["status"] == "failed") == ["broken.ply", "empty.ply"]
    run = next(row for row in read_rows(together / MANIFEST_NAME) if row["event"] == "run")
    assert run["settings"]["together"] == 4
    distance = {together: [], alone: []}
    for path in sorted(alone.rglob("scan*.ply")):
        scan = trimesh.load(scans / path.relative_to(alone), process=False).vertices
        for out in (together, alone):
            fitted = trimesh.load(out / path.relative_to(alone), process=False)
            distance[out].append(float(np.nanmean(inside_distance(scan, fitted.vertices, fitted.faces))))
    ratios = np.array(distance[together]) / np.array(distance[alone])
    assert len(ratios) == 10 and np.mean(distance[together]) <= 1.15 * np.mean(distance[alone]), distance
    assert ratios.max() <= 2.0, ratios


def test_a_pool_starts_its_workers_at_its_first_fit_and_before_handing_it_over():
    """A fit's timeout counts the fit: the first fit handed to a pool (new, or restarted) waits
    until all its workers (a fresh interpreter each, torch and statfit imported) have started, and
    then runs at once. A pool given no fit starts no worker."""
    import multiprocessing
    import time

    from statfit.batch.engines import _pid_after

    # an earlier test's pool may still be winding down a process for a moment: count only this pool's
    before = set(multiprocessing.active_children())
    engine = LocalPool(2)
    try:
        assert set(multiprocessing.active_children()) <= before
        for _ in range(2):                                  # new, then restarted
            began = time.perf_counter()
            future = engine.submit(_pid_after, 0.0)
            starting = time.perf_counter() - began
            workers = set(multiprocessing.active_children()) - before
            assert len(workers) >= 2
            began = time.perf_counter()
            assert engine.result(future) in {p.pid for p in workers}
            assert time.perf_counter() - began < starting     # no start-up left in the fit's own time
            engine.replace([], [])
    finally:
        engine.close()


def test_local_pool_fits_like_one_by_one_register_and_reruns_skip_what_is_done(scans, tmp_path):
    """One fit a program (``--together 1``, the CPU's default; a GPU's steps many together, which
    test_scans_registered_together_fit_as_one_by_one holds): the pool's outputs are the bytes that
    ``register`` writes."""
    out = tmp_path / "fits"
    alone = ("--together", "1")
    code, err = run_cli(["batch", "register", str(scans / "**" / "*.ply"), "--out-dir", str(out), "--workers", "2",
                         "--seed", "3", *alone, *FAST])
    assert code == 1, err  # two inputs are corrupt
    rows = fit_rows(out)
    assert sorted(Path(r["input"]).name for r in rows if r["status"] == "failed") == ["broken.ply", "empty.ply"]
    assert all(r["error"] and "\n" not in r["error"] for r in rows if r["status"] == "failed")
    done = sorted(r["output"] for r in rows if r["status"] == "done")
    assert len(done) == 10 and all(d.startswith(("left/", "right/")) for d in done)
    one = tmp_path / "one.ply"
    assert run_cli(["register", str(scans / "left" / "scan03.ply"), "--out", str(one), "--seed", "3", "-q",
                    *FAST])[0] == 0
    assert (out / "left" / "scan03.ply").read_bytes() == one.read_bytes()
    state = batch_status(out)
    assert (len(state.done), len(state.failed), len(state.pending)) == (10, 2, 0)
    # Rerun: only the two failures are tried again; a changed input is redone.
    (scans / "left" / "scan01.ply").write_bytes((scans / "left" / "scan01.ply").read_bytes())  # same bytes
    code, _ = run_cli(["batch", "register", str(scans / "**" / "*.ply"), "--out-dir", str(out), "--workers", "2",
                       "--seed", "3", *alone, *FAST])
    assert code == 1 and len(fit_rows(out)) == len(rows) + 2
    # New settings redo everything.
    code, _ = run_cli(["batch", "register", str(scans / "right" / "scan0[02].ply"), "--out-dir", str(out),
                       "--workers", "1", "--seed", "4", *FAST])
    assert code == 0 and len(fit_rows(out)) == len(rows) + 4


def test_a_killed_batch_resumes_without_redoing_what_it_recorded(scans, tmp_path):
    out = tmp_path / "fits"
    command = [sys.executable, "-m", "statfit_cli.main", "batch", "register", str(scans / "**" / "scan*.ply"),
               "--out-dir", str(out), "--workers", "2", "-q", "--iterations", "300", "--align", "none"]
    process = subprocess.Popen(command, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and len(fit_rows(out) if out.exists() else []) < 3:
        time.sleep(0.05)
    workers = [int(pid) for pid in Path(f"/proc/{process.pid}/task/{process.pid}/children").read_text().split()]
    process.send_signal(signal.SIGKILL)
    process.wait()
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and any(Path(f"/proc/{pid}").exists() for pid in workers):
        time.sleep(0.1)
    assert workers and not any(Path(f"/proc/{pid}").exists() for pid in workers), "workers outlived the batch"
    before = {r["input"] for r in fit_rows(out)}
    assert 3 <= len(before) < 10, "the kill came too late to test resuming"
    assert subprocess.run(command, stderr=subprocess.DEVNULL).returncode == 0
    after = [r["input"] for r in fit_rows(out)[len(before):]]
    assert not set(after) & before and len(set(after)) == len(after) == 10 - len(before)
    assert len(list(out.rglob("*.ply"))) == 10
    assert not list(out.rglob(".statfit-*"))  # no temporary file left behind


def test_sigterm_stops_the_batch_with_code_130_and_a_clean_manifest(scans, tmp_path):
    """A scheduler's SIGTERM after the first recorded fit. ``--together 1``: on a GPU a batch steps its
    scans together by default, and all ten then finish at once, before the signal (session 33's card)."""
    out = tmp_path / "fits"
    command = [sys.executable, "-m", "statfit_cli.main", "batch", "register", str(scans / "**" / "scan*.ply"),
               "--out-dir", str(out), "--workers", "1", "--together", "1", "--iterations", "300", "--align", "none"]
    process = subprocess.Popen(command, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and len(fit_rows(out) if out.exists() else []) < 1:
        time.sleep(0.05)
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 130 and "rerun the same command" in err
    lines = (out / MANIFEST_NAME).read_bytes().splitlines()
    assert all(json.loads(line) for line in lines)
    assert len(batch_status(out).pending) > 0


def test_dask_local_cluster_gives_the_same_outputs(scans, tmp_path):
    pytest.importorskip("distributed")
    local, dask = tmp_path / "local", tmp_path / "dask"
    pattern = str(scans / "**" / "*.ply")  # 12 scans, 2 of them corrupt
    assert run_cli(["batch", "register", pattern, "--out-dir", str(local), "--workers", "1", *FAST])[0] == 1
    code, err = run_cli(["batch", "register", pattern, "--out-dir", str(dask), "--cluster", "local", "--workers", "2",
                         *FAST])
    assert code == 1, err
    assert {r["output"]: r["status"] for r in fit_rows(local)} == {r["output"]: r["status"] for r in fit_rows(dask)}
    for output in local.rglob("*.ply"):
        assert output.read_bytes() == (dask / output.relative_to(local)).read_bytes()


@pytest.mark.parametrize("arguments, message", [
    (["--cluster", "big"], "--cluster takes 'local'"),
    (["--cluster", "local", "--scheduler", "tcp://x:1"], "either --scheduler"),
    (["--workers", "0"], "--workers"),
    (["--timeout", "0"], "--timeout"),
    (["--region", "nowhere"], "nowhere"),
])
def test_a_batch_that_cannot_start_says_why_in_one_line(scans, tmp_path, arguments, message):
    code, err = run_cli(["batch", "register", str(scans / "left" / "*.ply"), "--out-dir", str(tmp_path / "o"),
                         *arguments])
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_status_of_a_folder_without_a_batch(tmp_path):
    code, err = run_cli(["batch", "status", str(tmp_path)])
    assert code == 2 and "no batch" in err


def test_dask_replaces_the_worker_of_a_hung_fit(tmp_path):
    pytest.importorskip("distributed")
    from statfit.batch.engines import DaskPool

    for name in ("ok1", "hang", "ok2", "bad"):
        (tmp_path / f"{name}.ply").write_bytes(name.encode())
    items = plan_outputs(expand_inputs([str(tmp_path / "*.ply")]), tmp_path / "out")
    (tmp_path / "out").mkdir()
    engine = DaskPool("local", 2)
    try:
        report = run_batch(items, FitJob("register", None, None, resolve("none")), tmp_path / "out", engine,
                           timeout=4, work=copy_or_misbehave)
    finally:
        engine.close()
    assert report.done == 2
    assert dict((Path(s).stem, r) for s, r in report.failed) == {"hang": "timed out after 4 s", "bad": "bad is bad"}


def test_batch_render_fits_each_map_like_render(tmp_path):
    """Byte for byte as `render` fits the map alone (`--together 1`: on a GPU, batch steps maps
    together by default, whose sums run in another order)."""
    maps = tmp_path / "maps"
    maps.mkdir()
    for seed in (1, 2):
        assert run_cli(["synth", "normals", "--seed", str(seed), "--size", "64", "--out", str(maps / f"m{seed}.exr")])[0] == 0
    (maps / "m3.exr").write_bytes(b"not an exr")
    out = tmp_path / "fits"
    code, err = run_cli(["batch", "render", str(maps / "*.exr"), "--camera-from-header", "--out-dir", str(out),
                         "--workers", "2", "--iterations", "20", "--together", "1", "-q"])
    assert code == 1, err
    assert {r["output"]: r["status"] for r in fit_rows(out)} == {"m1.ply": "done", "m2.ply": "done", "m3.ply": "failed"}
    one = tmp_path / "one.ply"
    assert run_cli(["render", str(maps / "m2.exr"), "--out", str(one), "--iterations", "20", "-q"])[0] == 0
    assert (out / "m2.ply").read_bytes() == one.read_bytes()


def test_batch_render_reads_each_maps_own_camera(tmp_path):
    """PNG normal maps carry no camera: `--camera '{stem}.json'` gives each map its own, beside it.
    Byte for byte as `render MAP --camera ITS_CAMERA`; a map without its camera fails alone; a
    changed camera fits that map again, and only it; the report measures each against its own."""
    from PIL import Image

    from statfit.io.normalmap import read_normal_map

    maps = tmp_path / "maps"
    maps.mkdir()
    for seed in (1, 2, 3):
        exr = maps / f"m{seed}.exr"
        assert run_cli(["synth", "normals", "--seed", str(seed), "--yaw", str(10 * seed), "--size", "64", "--out",
                        str(exr), "--camera-out", str(maps / f"m{seed}.json")])[0] == 0
        normal_map = read_normal_map(exr)
        encoded = np.round((normal_map.normals + 1.0) / 2.0 * 255.0) * normal_map.mask[..., None]
        Image.fromarray(encoded.astype(np.uint8), "RGB").save(maps / f"m{seed}.png")
        exr.unlink()
    (maps / "m3.json").unlink()
    out = tmp_path / "fits"
    # no alignment (the slow part; test_batch_render_fits_each_map_like_render has it): each fit starts
    # at the template seen by its own camera
    command = ["batch", "render", str(maps / "*.png"), "--camera", "{stem}.json", "--out-dir", str(out), "--workers",
               "1", "--iterations", "20", "--align", "none", "--together", "1", "-q"]
    code, err = run_cli(command)
    assert code == 1, err
    rows = {row["output"]: row for row in fit_rows(out)}
    assert {name: row["status"] for name, row in rows.items()} == {"m1.ply": "done", "m2.ply": "done",
                                                                   "m3.ply": "failed"}
    assert f"no camera file {maps / 'm3.json'}" in rows["m3.ply"]["error"]
    one = tmp_path / "one.ply"
    assert run_cli(["render", str(maps / "m2.png"), "--camera", str(maps / "m2.json"), "--out", str(one),
                    "--iterations", "20", "--align", "none", "-q"])[0] == 0
    assert (out / "m2.ply").read_bytes() == one.read_bytes()
    camera = json.loads((maps / "m1.json").read_text())
    camera["K"][0][2] += 0.5                                   # the principal point half a pixel over
    (maps / "m1.json").write_text(json.dumps(camera))
    assert run_cli(command)[0] == 1
    assert [row["output"] for row in fit_rows(out)][3:] == ["m3.ply", "m1.ply"]     # m2 skipped
    assert run_cli(["batch", "report", str(out)])[0] == 0
    table = (out / "report.csv").read_text()
    assert table.count(",done,") == 2 and "degrees" in table


def test_a_pool_of_n_workers_runs_n_processes(tmp_path):
    for index in range(8):
        (tmp_path / f"slow{index}.ply").write_bytes(b"x")
    items = plan_outputs(expand_inputs([str(tmp_path / "*.ply")]), tmp_path / "out")
    (tmp_path / "out").mkdir()
    for workers in (1, 2):
        engine = LocalPool(workers)
        try:
            run_batch(items, FitJob("register", None, None, resolve("none")), tmp_path / "out", engine, force=True,
                      work=copy_or_misbehave)
        finally:
            engine.close()
        last = fit_rows(tmp_path / "out")[-8:]
        assert len({row["summary"]["worker"] for row in last}) <= workers
