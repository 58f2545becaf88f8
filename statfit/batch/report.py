"""A batch you can look at: one row per input of the latest run in a batch's folder — its status and
reason, its error against its own data, the register pose report, seconds and a thumbnail — as a
CSV and a self-contained HTML page (:mod:`statfit.batch.report_page`).

Errors are measured here, at report time, from the files: register — the distance of the scan
file's points to the fitted surface, in the scan's units; render — the angle between the map's
normals and the fit's, rendered with the map's camera, over the pixels both cover. Failures, rows
that cannot be checked (an output or input gone or corrupt: its reason says which) and outliers
(mean error above the batch's median + 3·MAD) come first.
"""
from __future__ import annotations

import csv
import io
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from statfit.batch.manifest import MANIFEST_NAME, latest_fits, read_rows
from statfit.batch.plan import map_camera_file
from statfit.errors import StatfitError
from statfit.geometry.metrics import measured_points, surface_distance
from statfit.io.image import image_bytes
from statfit.io.landmarks import read_landmarks
from statfit.io.mesh import read_mesh, read_points
from statfit.io.normalmap import camera_for_map, read_normal_map
from statfit.model.importers.cache import open_model
from statfit.model.statmodel import StatModel
from statfit.render.job import camera_space_normals
from statfit.render.preview import angular_error
from statfit.renderer.images import cropped, front_camera, mesh_with_points, normals_to_rgb, render_target

COLUMNS = ("input", "output", "status", "reason", "outlier", "error_mean", "error_median", "error_unit",
           "landmark_error", "pose_ambiguous", "pose_score", "pose_runner_up", "hair_share", "fit_residual",
           "fell_back", "seconds")
THUMBNAIL = 160             # pixels: the register view's side, the render pair's height
OUTLIER_MADS = 3.0          # mean error above median + this many MADs (of the batch's rows) is an outlier
PENDING = "not fitted yet: rerun the batch command to fit it"


@dataclass
class ReportRow:
    """One input's line of the report (``None``: not measured or not applicable)."""
    input: str
    output: str = ""
    status: str = "pending"
    reason: str = ""
    outlier: bool = False
    error_mean: float | None = None
    error_median: float | None = None
    error_unit: str = ""
    landmark_error: float | None = None
    pose_ambiguous: bool | None = None
    pose_score: float | None = None
    pose_runner_up: float | None = None
    hair_share: float | None = None
    fit_residual: float | None = None       # register's default: its fit's residual in model radii (fallback test)
    fell_back: bool | None = None           # and whether it refitted with the fallback's method
    seconds: float | None = None
    thumbnail: bytes | None = field(default=None, repr=False)   # PNG

    @property
    def attention(self) -> int:
        """0 failed, 1 not checkable, 2 outlier, 3 pending, 4 fine: the report's order."""
        if self.status == "failed":
            return 0
        if self.status == "done" and self.reason:
            return 1
        return 2 if self.outlier else 3 if self.status == "pending" else 4


@dataclass
class Batch:
    """The latest run recorded in a batch folder: its settings and key, its inputs in order, and the
    latest ``fit`` line of every input."""
    out_dir: Path
    settings: dict[str, Any]
    key: str
    inputs: list[str]
    fits: dict[str, dict[str, Any]]

    @property
    def command(self) -> str:
        return str(self.settings.get("command", "register"))

    @cached_property
    def model(self) -> StatModel:
        path = self.settings.get("model")
        return open_model(Path(path) if path else None, self.settings.get("k"))


def read_batch(out_dir: Path) -> Batch:
    """The latest run in ``out_dir``; a StatfitError if the folder is missing, not a folder, or holds
    no batch."""
    if not out_dir.exists():
        raise StatfitError(f"no such folder: {out_dir}")
    if not out_dir.is_dir():
        raise StatfitError(f"{out_dir} is not a folder (give a batch's output folder)")
    path = out_dir / MANIFEST_NAME
    if not path.is_file():
        raise StatfitError(f"no batch in {out_dir} (no {MANIFEST_NAME})")
    try:
        rows = read_rows(path)
    except OSError as exc:
        raise StatfitError(f"cannot read {path}: {exc.strerror}") from None
    runs = [row for row in rows if row["event"] == "run"]
    if not runs:
        raise StatfitError(f"{path} records no batch run")
    run = runs[-1]
    return Batch(out_dir, run.get("settings") or {}, run.get("key", ""), list(dict.fromkeys(run.get("inputs", []))),
                 latest_fits(rows))


def report_rows(batch: Batch, on_row: Callable[[int, int], None] | None = None) -> list[ReportRow]:
    """Every input's row, failures and outliers first; ``on_row(done, total)`` after each."""
    rows = []
    for index, source in enumerate(batch.inputs):
        rows.append(input_row(batch, source))
        if on_row is not None:
            on_row(index + 1, len(batch.inputs))
    mark_outliers(rows)
    return ordered(rows)


def ordered(rows: list[ReportRow]) -> list[ReportRow]:
    """Failed, not checkable, outliers (worst first), pending, the rest; input order within each."""
    return sorted(rows, key=lambda row: (row.attention, -(row.error_mean or 0.0) if row.outlier else 0.0))


def input_row(batch: Batch, source: str) -> ReportRow:
    """One input's row: the manifest's record, then the error and thumbnail measured from the files
    (a file that cannot be read becomes the row's reason)."""
    fit = batch.fits.get(source)
    if fit is None or fit.get("key") != batch.key or fit.get("status") not in ("done", "failed"):
        return ReportRow(source, reason=PENDING)
    summary = fit.get("summary") or {}
    pose = summary.get("pose") or {}
    fallback = summary.get("fallback") or {}
    row = ReportRow(source, str(fit.get("output", "")), fit["status"], fit.get("error") or "",
                    seconds=_number(fit.get("seconds")), pose_ambiguous=pose.get("ambiguous"),
                    pose_score=_number(pose.get("score")), pose_runner_up=_number(pose.get("runner_up")),
                    hair_share=_number(pose.get("hair_share")), fit_residual=_number(fallback.get("residual")),
                    fell_back=fallback.get("used"))
    if row.status != "done":
        return row
    try:
        vertices, faces = _read("output", read_mesh, batch.out_dir / row.output)
        if batch.command == "render":
            measure_render(row, batch, vertices, faces)
        else:
            measure_register(row, vertices, faces, summary.get("model_to_scan"))
        landmarks = summary.get("landmarks") or batch.settings.get("options", {}).get("landmarks")
        if isinstance(landmarks, str) and batch.model.landmarks is not None:
            row.landmark_error = landmark_error(vertices, batch.model.landmarks,
                                                _read("landmarks", read_landmarks, landmarks))
    except StatfitError as exc:
        row.reason = f"cannot check: {exc}"
    except Exception as exc:  # a file no reader foresaw: this row says so, the report goes on
        row.reason = f"cannot check: {type(exc).__name__}: {exc}".splitlines()[0]
    return row


def _read(what: str, reader: Callable[[Any], Any], path: Any) -> Any:
    try:
        return reader(path)
    except StatfitError as exc:
        raise StatfitError(f"{what}: {exc}") from None


def _number(value: Any) -> float | None:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def measure_register(row: ReportRow, vertices: np.ndarray, faces: np.ndarray, model_to_scan: Any) -> None:
    """Distance of the scan file's points (at most ``MEASURED_POINTS`` of them) to the fitted surface
    (``vertices`` (N, 3), ``faces`` (F, 3)), and a front view of the fit with the points over it."""
    points = _read("input", read_points, row.input)
    points = measured_points(points)
    distance = surface_distance(points, vertices, faces)
    row.error_mean, row.error_median, row.error_unit = float(distance.mean()), float(np.median(distance)), "scan units"
    turn = np.eye(3) if model_to_scan is None else np.asarray(model_to_scan, dtype=np.float64)[:3, :3]
    image, shown = mesh_with_points(vertices, faces, points, distance, front_camera(vertices, turn, THUMBNAIL))
    row.thumbnail = image_bytes(cropped(image, shown), ".png")


def measure_render(row: ReportRow, batch: Batch, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Angle between the map's normals and the fit's (rendered with the map's camera) over the
    pixels both cover, and the two normal maps side by side."""
    options = batch.settings.get("options") or {}
    normal_map = _read("input", read_normal_map, row.input)
    camera = _read("camera", lambda source: camera_for_map(normal_map, map_camera_file(options.get("camera"), source),
                                                            source), row.input)
    target = camera_space_normals(normal_map, camera, options.get("normal_space", "world"),
                                  options.get("normal_convention", "opencv"))
    fitted, covered = render_target(vertices, faces, camera, space="camera")
    both = covered & normal_map.mask
    if not both.any():
        raise StatfitError("the fit covers none of the map's pixels")
    angles = angular_error(fitted.astype(np.float64), target)[both]
    row.error_mean, row.error_median, row.error_unit = float(angles.mean()), float(np.median(angles)), "degrees"
    seen = covered | normal_map.mask
    pair = [shrunk(cropped(normals_to_rgb(image, mask), seen)) for image, mask in ((target, normal_map.mask),
                                                                                   (fitted, covered))]
    gap = np.ones((pair[0].shape[0], 4, 3))
    row.thumbnail = image_bytes(np.concatenate([pair[0], gap, pair[1]], axis=1), ".png")


def shrunk(image: np.ndarray, height: int = THUMBNAIL) -> np.ndarray:
    """``image`` (H, W, 3) averaged over square blocks to about ``height`` rows."""
    step = max(1, int(np.ceil(image.shape[0] / height)))
    rows, columns = image.shape[0] // step * step, image.shape[1] // step * step
    blocks = image[:rows, :columns].reshape(rows // step, step, columns // step, step, image.shape[2])
    return blocks.mean(axis=(1, 3))


def landmark_error(vertices: np.ndarray, indices: np.ndarray, landmarks: np.ndarray) -> float:
    """Mean distance between the fit's landmark vertices (``vertices`` (N, 3) at ``indices`` (L,))
    and the data's ``landmarks`` (L, 3), over the present (finite) rows."""
    if landmarks.shape != (len(indices), 3):
        raise StatfitError(f"landmarks: expected {len(indices)} rows of x y z, got an array of shape {landmarks.shape}")
    present = np.isfinite(landmarks).all(axis=1)
    if not present.any():
        raise StatfitError("landmarks: none present")
    return float(np.linalg.norm(vertices[indices[present]] - landmarks[present], axis=1).mean())


def mark_outliers(rows: list[ReportRow]) -> None:
    """Flag the rows whose mean error lies above the median + OUTLIER_MADS · MAD of the measured rows."""
    measured = [row for row in rows if row.error_mean is not None and not row.reason]
    errors = np.array([row.error_mean for row in measured])
    if errors.size == 0:
        return
    median = np.median(errors)
    limit = median + OUTLIER_MADS * np.median(np.abs(errors - median))
    for row, outlier in zip(measured, errors > limit):
        row.outlier = bool(outlier)


def csv_text(rows: list[ReportRow]) -> str:
    """The rows as CSV, one per input, with a header of COLUMNS (booleans 1/0, missing values empty)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(COLUMNS)
    writer.writerows([_cell(getattr(row, column)) for column in COLUMNS] for row in rows)
    return buffer.getvalue()


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return str(int(value))
    return f"{value:.6g}" if isinstance(value, float) else str(value)
