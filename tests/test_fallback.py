"""register's default falls back to ``laplacian`` where its fit cannot explain the scan it saw
(docs/method.md, "When the model cannot explain the scan"; docs/studies.md §23)."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import trimesh

from statfit.core.methods import FALLBACK_CODE, FALLBACK_RESIDUAL, Fallback, fallback, resolve
from statfit.errors import StatfitWarning
from statfit.geometry.closest import open_edges
from statfit.registration.job import register
from statfit.structures.frame import Frame
from statfit.synth.sample import sample_target, scan_from_view

from conftest import run_cli

ALWAYS = Fallback("laplacian", 0.0)     # fires on any scan: the refit itself is what is tested


@pytest.fixture(scope="module")
def scan(embedded_model):
    """A person of the embedded model seen from one side (the demo's case), 4,300 points."""
    rng = np.random.default_rng(3)
    target = sample_target(embedded_model, rng, sigma=1.5)
    return scan_from_view(target, embedded_model.faces, rng, 4300, 30.0)


def test_only_the_shipped_default_pipeline_has_a_fallback():
    shipped = Fallback("laplacian", FALLBACK_RESIDUAL, FALLBACK_CODE)
    assert fallback("default") == shipped == fallback("default", iterations=None)
    assert fallback("default", iterations=100) is None           # a tuned-by-hand default was not measured
    assert fallback("default", "paper") is None
    assert fallback("laplacian") is None and fallback("pca") is None
    assert fallback("default", job="render") is None


def test_a_scan_the_model_explains_keeps_the_default_fit_to_the_bit(embedded_model, scan):
    gated = register(embedded_model, scan, threads=1)
    plain = register(embedded_model, scan, threads=1, fallback=False)
    assert gated.fallback["method"] == "laplacian" and gated.fallback["threshold"] == FALLBACK_RESIDUAL
    assert not gated.fallback["used"] and gated.fallback["residual"] < 0.1 * FALLBACK_RESIDUAL
    assert gated.fallback["code"] < 0.5 * FALLBACK_CODE and gated.fallback["code_threshold"] == FALLBACK_CODE
    assert plain.fallback is None
    np.testing.assert_array_equal(gated.vertices, plain.vertices)
    assert gated.stages == resolve("default") and gated.iterations == plain.iterations


def test_the_residual_is_the_scans_mean_distance_to_the_fit_in_the_posed_models_radii(embedded_model, scan):
    """Against libigl's closest points on the fitted mesh, in the scan's frame and units: the
    embedded head is closed, so no point lies beyond an open boundary and every point counts."""
    import igl
    import torch

    assert not open_edges(torch.as_tensor(embedded_model.faces)).any()
    result = register(embedded_model, scan, threads=1, iterations=40, fallback=ALWAYS)
    # the refit is laplacian's; the residual reported is the default's: refit its 40 iterations alone
    default = register(embedded_model, scan, threads=1, iterations=40, fallback=False)
    squared, _, _ = igl.point_mesh_squared_distance(scan, default.vertices, embedded_model.faces.astype(np.int64))
    distance = np.sqrt(squared)
    radius = Frame.of(embedded_model.template).scale * default.transform.scale
    assert result.fallback["residual"] == pytest.approx(distance.mean() / radius, rel=1e-5)


def test_the_code_is_the_rms_of_the_fits_least_squares_coefficients_in_standard_deviations(embedded_model, scan):
    """Against a least-squares solve of the fit (the model's frame) on the model's modes, in std units."""
    result = register(embedded_model, scan, threads=1, iterations=40)
    offset = (result.transform.inverse_apply(result.vertices) - embedded_model.template).reshape(-1)
    coefficients, *_ = np.linalg.lstsq(embedded_model.basis * embedded_model.std, offset, rcond=None)
    assert result.fallback is None          # overridden settings: the shipped fallback does not apply
    code = register(embedded_model, scan, threads=1, iterations=40,
                    fallback=Fallback("laplacian", np.inf)).fallback["code"]
    assert code == pytest.approx(np.sqrt(np.mean(coefficients ** 2)), rel=1e-4)


def test_a_shape_the_model_would_need_unusual_coefficients_for_is_refitted(embedded_model, scan):
    with pytest.warns(StatfitWarning, match="standard deviations per mode.*refitted with laplacian"):
        result = register(embedded_model, scan, threads=1, iterations=40, fallback=Fallback("laplacian", np.inf, 0.0))
    assert result.fallback["used"] and result.stages == resolve("laplacian")


def test_a_fit_that_cannot_explain_the_scan_is_laplacians_fit_from_the_same_pose(embedded_model, scan):
    records = []
    with pytest.warns(StatfitWarning, match="cannot make.*refitted with laplacian"):
        result = register(embedded_model, scan, threads=1, fallback=ALWAYS,
                          on_record=lambda iteration, terms: records.append(iteration))
    laplacian = register(embedded_model, scan, "laplacian", threads=1)
    # the refit's records follow the first fit's, numbered on (a log reads as one run)
    assert records == sorted(records) and len(set(records)) == len(records)
    assert records[-1] == result.iterations - 1
    assert result.fallback["used"]
    np.testing.assert_array_equal(result.vertices, laplacian.vertices)
    assert result.stages == resolve("laplacian")
    default = register(embedded_model, scan, threads=1, fallback=False)
    assert result.iterations == default.iterations + laplacian.iterations


def test_a_fit_kept_to_a_region_has_no_fallback(embedded_model, scan):
    result = register(embedded_model, scan, threads=1, region="face", iterations=20, fallback=ALWAYS)
    assert result.fallback is None and result.stages == resolve("default", iterations=20)


def test_the_cli_reports_the_fallback_and_turns_it_off(tmp_path, embedded_model, scan):
    path = tmp_path / "scan.ply"
    trimesh.PointCloud(scan).export(path)
    summaries = {}
    for name, options in {"on": [], "off": ["--no-fallback"], "tuned": ["--iterations", "40"]}.items():
        log = tmp_path / f"{name}.jsonl"
        code, err = run_cli(["register", str(path), "--out", str(tmp_path / f"{name}.ply"), "--log", str(log), "-q",
                             *options])
        assert code == 0, err
        summaries[name] = json.loads(log.read_text().splitlines()[-1])
    assert summaries["on"]["fallback"]["threshold"] == FALLBACK_RESIDUAL and not summaries["on"]["fallback"]["used"]
    assert summaries["on"]["fallback"]["code_threshold"] == FALLBACK_CODE
    assert summaries["off"]["fallback"] is None and summaries["tuned"]["fallback"] is None
    assert (tmp_path / "on.ply").read_bytes() == (tmp_path / "off.ply").read_bytes()


def test_a_batch_records_each_fits_test_and_its_report_shows_it(tmp_path, embedded_model, scan):
    from statfit.batch.manifest import MANIFEST_NAME, read_rows

    trimesh.PointCloud(scan).export(tmp_path / "scan.ply")
    out = tmp_path / "fits"
    for argv in (["batch", "register", str(tmp_path / "scan.ply"), "--out-dir", str(out), "--workers", "1", "-q"],
                 ["batch", "report", str(out)]):
        code, err = run_cli(argv)
        assert code == 0, err
    [fit] = [row for row in read_rows(out / MANIFEST_NAME) if row["event"] == "fit"]
    report = fit["summary"]["fallback"]
    assert report["threshold"] == FALLBACK_RESIDUAL and not report["used"]
    [row] = list(csv.DictReader((out / "report.csv").read_text().splitlines()))
    assert float(row["fit_residual"]) == pytest.approx(report["residual"], rel=1e-5) and row["fell_back"] == "0"


def test_points_near_an_open_border_are_left_out_of_the_residual():
    """A flat square sheet (z = 0, 21 × 21 vertices over [0, 1]²) and points over and beside it:
    the distance is the height where the point's foot lies farther than the band from every border
    vertex, NaN where it lies nearer, and NaN past the sheet's edge whatever the band."""
    from statfit.geometry.metrics import inside_distance

    grid = np.linspace(0.0, 1.0, 21)
    x, y = np.meshgrid(grid, grid, indexing="ij")
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    index = np.arange(x.size).reshape(21, 21)
    a, b, c, d = index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    rng = np.random.default_rng(0)
    feet = rng.uniform(0.0, 1.0, (400, 2))
    height = rng.uniform(-0.3, 0.3, 400)
    points = np.column_stack([feet, height])
    border = vertices[(vertices[:, 0] % 1 == 0) | (vertices[:, 1] % 1 == 0)][:, :2]
    to_border = np.linalg.norm(feet[:, None] - border[None], axis=-1).min(axis=1)
    past = np.array([[1.2, 0.5, 0.1], [0.5, -0.3, 0.0]])
    for band in (0.0, 0.1, 0.25):
        distance = inside_distance(np.concatenate([points, past]), vertices, faces, border_band=band)
        kept = to_border >= band
        np.testing.assert_allclose(distance[:400][kept], np.abs(height[kept]), atol=1e-12)
        assert np.isnan(distance[:400][~kept]).all() and np.isnan(distance[400:]).all()
        assert kept.sum() < 400 or band == 0.0


def test_a_face_masks_neck_does_not_send_its_fit_to_laplacian(embedded_model):
    """docs/studies.md §34/§35: the embedded head's face cut, a realistic scan of its own person
    with neck and shoulders (seed 2 of studies/mask_clutter.py). The scan's points under the
    chin, which the fit leaves out, put the mean distance of every point whose foot is not on
    the border at 4.2% of the radius, over the 2% threshold; left out within 0.1 radii of the
    border, 0.8%: the default's fit is kept (its error 0.38–0.41 mm; the refit's 0.52). With numpy
    1.26 and SciPy 1.11, the oldest pyproject allows, the kept fit's error is 0.515 mm: rounding
    moves a fit that much for nothing (§29), so the bound is the fit's sanity, 0.6 mm (1% of the
    mask's RMS radius, 59 mm), and the claim is the decision."""
    from statfit.geometry.metrics import inside_distance
    from statfit.model.cut import region_part
    from statfit.structures.scan import Scan
    from statfit.synth.scanner import realistic_scan

    with pytest.warns(StatfitWarning, match="landmarks"):
        mask = region_part(embedded_model, "face")
    rng = np.random.default_rng(2002)
    made = realistic_scan(mask.sample(rng), mask.faces, rng, yaw_deg=float(rng.uniform(-30, 30)), clutter=0.5,
                          clutter_parts=("neck",), units="mm")
    result = register(mask, Scan.from_mesh(made.vertices, made.faces), threads=1)
    assert not result.fallback["used"] and result.fallback["residual"] < 0.5 * FALLBACK_RESIDUAL
    radius = Frame.of(mask.template).scale * result.transform.scale
    every = inside_distance(made.vertices, result.vertices, mask.faces)
    assert np.nanmean(every) / radius > FALLBACK_RESIDUAL          # the residual before §35's band
    assert np.linalg.norm(result.vertices - made.truth, axis=1).mean() < 0.6
