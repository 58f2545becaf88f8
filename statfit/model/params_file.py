"""The params file (``--params FILE.json|.npz``): a fit's code in the model — the similarity, the
coefficients and the off-span residual — tied to the model it was made with. Format: docs/formats.md
("Params file"). Written with reproducible bytes; read back exactly (JSON floats round-trip)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from statfit.errors import StatfitError
from statfit.geometry.align import Similarity
from statfit.io.files import existing_file, params_suffix
from statfit.io.npz import npz_bytes, read_npz
from statfit.model.params import (Projection, canonical_signs, check_fingerprint, model_fingerprint,
                                  off_span_summary)
from statfit.model.statmodel import StatModel

FORMAT, VERSION = "statfit-params", 1
MAX_BYTES = 64 << 20
ROTATION_TOLERANCE = 1e-6
# Coefficients (standard deviations) beyond this are no person's: a damaged or foreign file.
IMPLAUSIBLE_COEFFICIENT = 1e3


def params_record(model: StatModel, projection: Projection) -> dict:
    """The params file's content as plain JSON values."""
    t = projection.transform
    record = {"format": FORMAT, "version": VERSION, "model": {"source": str(model.source), **model_fingerprint(model)},
              "similarity": {"scale": float(t.scale), "rotation": np.asarray(t.rotation, float).tolist(),
                             "rotation_deg": Rotation.from_matrix(t.rotation).as_rotvec(degrees=True).tolist(),
                             "translation": np.asarray(t.translation, float).tolist(),
                             "matrix": t.as_matrix().tolist(), "units_factor": projection.units_factor},
              "coefficients": (projection.coefficients * canonical_signs(model)).tolist()}
    if projection.off_span is not None:
        record["off_span"] = off_span_summary(model, projection.off_span)
    return record


def params_bytes(model: StatModel, projection: Projection, path: str | Path) -> bytes:
    """The params file for ``path`` (.json: indented JSON; .npz: arrays, docs/formats.md)."""
    record = params_record(model, projection)
    if params_suffix(path) == ".json":
        return ("{\n" + ",\n".join(f" {json.dumps(key)}: {json.dumps(value)}" for key, value in record.items())
                + "\n}\n").encode()
    sim, span = record["similarity"], record.get("off_span", {"rms": math.nan, "max": math.nan, "regions": {}})
    units = sim["units_factor"]
    return npz_bytes({
        "format": np.array(FORMAT), "version": np.array(VERSION), "model_source": np.array(record["model"]["source"]),
        **{f"model_{key}": np.array(record["model"][key]) for key in ("vertices", "faces", "modes", "sha256")},
        "scale": np.array(sim["scale"]), "rotation": np.array(sim["rotation"]),
        "translation": np.array(sim["translation"]), "units_factor": np.array(math.nan if units is None else units),
        "coefficients": np.array(record["coefficients"]), "off_span_rms": np.array(span["rms"]),
        "off_span_max": np.array(span["max"]), "region_names": np.array(list(span["regions"]), dtype=str),
        "region_rms": np.array([r["rms"] for r in span["regions"].values()], dtype=float),
        "region_max": np.array([r["max"] for r in span["regions"].values()], dtype=float)})


def read_params(path: str | Path, model: StatModel) -> Projection:
    """The code in the params file ``path``, checked against ``model`` (counts, hash) and for its
    form (one line naming what is wrong); ``off_span`` is None."""
    path = existing_file(path, "params file")
    suffix = params_suffix(path)
    if path.stat().st_size > MAX_BYTES:
        raise StatfitError(f"{path} is larger than {MAX_BYTES >> 20} MiB: not a params file")
    record = _json_record(path) if suffix == ".json" else _npz_record(path)
    if not isinstance(record, dict) or record.get("format") != FORMAT:
        raise StatfitError(f"{path} is not a statfit params file (no \"format\": \"{FORMAT}\")")
    if record.get("version") != VERSION:
        raise StatfitError(f"{path}: params version {record.get('version')!r} is not supported (expected {VERSION})")
    if not isinstance(record.get("model"), dict):
        raise StatfitError(f"{path}: no \"model\" object (vertices, faces, modes, sha256)")
    check_fingerprint(model, record["model"], str(path))
    sim = record.get("similarity")
    if not isinstance(sim, dict):
        raise StatfitError(f"{path}: no \"similarity\" object")
    scale = _numbers(sim.get("scale"), (), path, "similarity.scale")
    rotation = _numbers(sim.get("rotation"), (3, 3), path, "similarity.rotation")
    translation = _numbers(sim.get("translation"), (3,), path, "similarity.translation")
    coefficients = _numbers(record.get("coefficients"), (model.num_modes,), path, "coefficients")
    if not scale > 0:
        raise StatfitError(f"{path}: similarity.scale must be positive, got {float(scale):g}")
    if (largest := float(np.abs(coefficients).max(initial=0.0))) > IMPLAUSIBLE_COEFFICIENT:
        raise StatfitError(f"{path}: a coefficient of {largest:.3g} standard deviations describes no person "
                           f"(fits of people far outside a model reach tens; the limit is {IMPLAUSIBLE_COEFFICIENT:g})")
    if (np.abs(rotation @ rotation.T - np.eye(3)).max() > ROTATION_TOLERANCE
            or abs(np.linalg.det(rotation) - 1) > ROTATION_TOLERANCE):
        raise StatfitError(f"{path}: similarity.rotation is not a rotation matrix (orthonormal, determinant 1)")
    units = sim.get("units_factor")
    units = None if units is None or (isinstance(units, float) and math.isnan(units)) else float(units)
    return Projection(coefficients * canonical_signs(model), Similarity(float(scale), rotation, translation),
                      None, units)


def _json_record(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise StatfitError(f"{path} is not valid JSON: {exc}") from None


def _npz_record(path: Path) -> dict:
    arrays = read_npz(path, "params")
    def value(key: str):
        return arrays[key].tolist() if key in arrays else None

    def scalar(key: str):   # npz_bytes stores a scalar as a 1-element array
        return arrays[key].reshape(-1)[0].item() if key in arrays and arrays[key].size == 1 else value(key)

    units = scalar("units_factor")
    return {"format": scalar("format"), "version": scalar("version"),
            "model": {key: scalar(f"model_{key}") for key in ("vertices", "faces", "modes", "sha256")},
            "similarity": {"scale": scalar("scale"), "rotation": value("rotation"), "translation": value("translation"),
                           "units_factor": None if not isinstance(units, float) or math.isnan(units) else units},
            "coefficients": value("coefficients")}


def _numbers(value, shape: tuple[int, ...], path: Path, name: str) -> np.ndarray:
    """``value`` as a finite float64 array of ``shape``, or one line naming ``name``."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise StatfitError(f"{path}: {name} must be numbers of shape {shape}") from None
    if array.shape != shape:
        raise StatfitError(f"{path}: {name} has shape {array.shape}, expected {shape}")
    if not np.isfinite(array).all():
        raise StatfitError(f"{path}: {name} has NaN or infinite values")
    return array
