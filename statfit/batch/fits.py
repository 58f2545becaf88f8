"""One fit as a job a worker process runs: the settings travel once (a small picklable
:class:`FitJob`), the worker opens the model once and keeps it, and each input comes back as the
output's bytes or a one-line error — never an exception that could stop the batch."""
from __future__ import annotations

import ctypes
import os
import time
import warnings
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from statfit import __version__
from statfit.errors import StatfitError, one_line
from statfit.model.importers.cache import open_model
from statfit.render.job import reconstruct
from statfit.render.many import reconstruct_many
from statfit.renderer import Camera
from statfit.structures.normal_map import NormalMap
from statfit.batch.plan import STEM, companion_file, map_camera_file
from statfit.io.landmarks import read_landmarks
from statfit.io.mesh import load_scan, mesh_bytes
from statfit.io.normalmap import camera_for_map, read_normal_map
from statfit.model.statmodel import StatModel
from statfit.geometry.support import scan_support, view_support
from statfit.model.params import project, vertex_fields
from statfit.model.params_file import params_bytes
from statfit.core.stages import Fit
from statfit.registration.job import register
from statfit.registration.many import register_many
from statfit.structures.scan import Scan
from statfit.core.methods import Fallback
from statfit.core.settings import Settings
from statfit.core.together import FitOutcome
from statfit.core.threads import flush_denormals_everywhere, limit_threads

COMMANDS = ("register", "render")


@dataclass(frozen=True)
class FitJob:
    """What every input of a batch is fitted with.

    ``command``: register (inputs are scans) or render (inputs are normal maps); ``model``: the
    model file (None: the embedded one) and ``k`` modes; ``stages``: the resolved pipeline;
    ``options``: the command's keyword arguments (align, trim, seed, camera, ...); ``threads``:
    per fit (None: chosen from the problem, at most ``max_threads``); ``model_digest``: the model
    file's content hash, so a changed model redoes the batch; ``fallback``: register's
    (:class:`statfit.core.methods.Fallback`), None for none; ``landmarks``: register's template of each
    scan's landmarks file (:func:`statfit.batch.plan.companion_file`), None for none. A render job's
    ``options["camera"]`` is one camera file for every map, a template of each map's own (with
    ``{stem}``), or None (each map's header)."""
    command: str
    model: str | None
    k: int | None
    stages: tuple[Settings, ...]
    options: dict[str, Any] = field(default_factory=dict)
    threads: int | None = None
    max_threads: int | None = None
    device: str = "cpu"
    model_digest: str = ""
    params: bool = False
    fallback: Fallback | None = None
    together: int = 1
    landmarks: str | None = None

    @property
    def companion(self) -> tuple[str, str] | None:
        """Each input's own companion file, whose bytes its fit depends on: (the template, what the
        file holds) — register's landmarks, render's camera named with ``{stem}`` — or None."""
        if self.landmarks:
            return self.landmarks, "landmarks"
        camera = self.options.get("camera")
        if self.command == "render" and camera is not None and STEM in camera:
            return camera, "camera"
        return None

    def settings(self) -> dict[str, Any]:
        """Everything that decides an output, as plain JSON (the manifest's settings key)."""
        return dict(command=self.command, model=self.model, model_digest=self.model_digest, k=self.k, stages=[s.describe() for s in self.stages],
                    options=self.options, device=self.device, statfit=__version__,
                    **({"params": True} if self.params else {}),
                    **({"fallback": asdict(self.fallback)} if self.fallback else {}),
                    **({"together": self.together} if self.together > 1 else {}),
                    **({"landmarks": self.landmarks} if self.landmarks else {}))


@dataclass
class Outcome:
    """One input's result: the output's bytes and the fit's summary, or a one-line ``error``;
    ``extras``: files written beside the output, by the suffix that replaces its own
    (``.params.json``)."""
    data: bytes | None
    summary: dict[str, Any]
    error: str | None
    seconds: float
    extras: dict[str, bytes] = field(default_factory=dict)


@lru_cache(maxsize=2)
def _model(path: str | None, k: int | None) -> StatModel:
    return open_model(Path(path) if path else None, k)


# glibc's mallopt parameters, and what a fit's allocator needs: large blocks kept for reuse.
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
KEEP_MAPPED_BYTES, KEEP_FREED_BYTES = 32 << 20, 64 << 20
MALLOC_ENVIRONMENT = ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TOP_PAD_")


def prepare_worker(max_threads: int | None = None) -> None:
    """Set up a worker process: subnormals flushed before any parallel kernel, threads capped,
    freed memory kept for reuse (:func:`keep_freed_memory`)."""
    flush_denormals_everywhere()
    limit_threads(max_threads)
    keep_freed_memory()


def keep_freed_memory() -> bool:
    """Undo a fixed malloc threshold in this process's environment (Dask starts its workers with
    MALLOC_TRIM_THRESHOLD_=65536). Any of these variables turns glibc's adaptive thresholds off, so
    every tensor a fit frees is returned to the system and the next is page-faulted anew: a render fit
    ran 2.1× slower (14.5 → 30.3 s). Sets the thresholds the adaptive ones settle at (32 MiB mmap,
    64 MiB trim); True if it did (glibc only, and only when such a variable is set)."""
    if not any(name in os.environ for name in MALLOC_ENVIRONMENT):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:     # not glibc: the variables mean nothing there
        return False
    return bool(libc.mallopt(M_MMAP_THRESHOLD, KEEP_MAPPED_BYTES) and libc.mallopt(M_TRIM_THRESHOLD, KEEP_FREED_BYTES))


PARAMS_SUFFIX = ".params.json"


def _fit(job: FitJob, source: str, model: StatModel) -> tuple[bytes, dict[str, Any], dict[str, bytes]]:
    observed = _read(job, source)
    common = dict(stages=job.stages, device=job.device, threads=job.threads)
    if job.command == "register":
        landmarks = _landmarks(job, source)
        result = register(model, observed, **common, **job.options, fallback=job.fallback,
                          landmarks=None if landmarks is None else landmarks[1])
        return _with_landmarks(_fitted(job, model, observed, result), landmarks)
    result = reconstruct(model, *observed, **common, **_render_options(job))
    return _fitted(job, model, observed, result)


def _landmarks(job: FitJob, source: str) -> tuple[Path, np.ndarray] | None:
    """The scan's landmarks file (``job.landmarks``'s template) and its rows (L, 3), or None."""
    if job.landmarks is None:
        return None
    path = companion_file(Path(source), job.landmarks)
    return path, read_landmarks(path)


def _with_landmarks(fitted: tuple[bytes, dict[str, Any], dict[str, bytes]], landmarks: tuple[Path, np.ndarray] | None
                    ) -> tuple[bytes, dict[str, Any], dict[str, bytes]]:
    """The fit's output with the landmarks file it used named in its summary (as ``register``'s)."""
    if landmarks is not None:
        fitted[1]["landmarks"] = str(landmarks[0].resolve())
    return fitted


def _read(job: FitJob, source: str) -> Scan | tuple[NormalMap, Camera]:
    """What ``job`` fits from ``source``: a scan, or a normal map and its camera."""
    if job.command == "register":
        return load_scan(source, job.options.get("seed", 0))
    if job.command == "render":
        normal_map = read_normal_map(source)
        return normal_map, camera_for_map(normal_map, map_camera_file(job.options.get("camera"), source), source)
    raise StatfitError(f"unknown batch command {job.command!r}; choose one of {', '.join(COMMANDS)}")


def _render_options(job: FitJob) -> dict[str, Any]:
    """``reconstruct``'s options of a render job (the camera is read with the map)."""
    return {name: value for name, value in job.options.items() if name != "camera"}


def _fitted(job: FitJob, model: StatModel, observed: Scan | tuple[NormalMap, Camera], result: Fit
            ) -> tuple[bytes, dict[str, Any], dict[str, bytes]]:
    """The output of ``result``, the fit of ``observed`` (what :func:`_read` gave)."""
    if job.command == "register":
        pose = {"model_to_scan": result.transform.as_matrix().tolist(), "pose": result.pose,
                "fallback": result.fallback}
        return _output(job, model, result, pose, scan_support(result.vertices, observed.points))
    normal_map, camera = observed
    pose = {"model_to_world": result.transform.as_matrix().tolist()}
    return _output(job, model, result, pose, view_support(result.vertices, model.faces, [(camera, normal_map.mask)]))


def _output(job: FitJob, model: StatModel, result: Fit, pose: dict[str, Any], support: tuple
            ) -> tuple[bytes, dict[str, Any], dict[str, bytes]]:
    """The fit's mesh (with its per-vertex fields), its summary and the files beside it."""
    summary = dict(iterations=result.iterations, final_loss=result.loss, fit_seconds=result.seconds, **pose)
    projection = project(model, result.vertices, result.transform, (result.pose or {}).get("units_factor"))
    extras = {PARAMS_SUFFIX: params_bytes(model, projection, "fit" + PARAMS_SUFFIX)} if job.params else {}
    return mesh_bytes(result.vertices, model.faces, "ply", vertex_fields(projection, *support)), summary, extras


def run_job(job: FitJob, source: str) -> Outcome:
    """Fit one input; every failure becomes the outcome's one-line error."""
    started = time.perf_counter()
    prepare_worker(job.max_threads)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        outcome = _guarded(lambda: _fit(job, source, _model(job.model, job.k)))
    if caught:
        outcome.summary["warnings"] = [str(w.message) for w in caught]
    outcome.seconds = time.perf_counter() - started
    return outcome


def run_group(job: FitJob, sources: list[str]) -> list[Outcome]:
    """Fit ``sources`` together (:func:`statfit.registration.many.register_many`,
    :func:`statfit.render.many.reconstruct_many`): one outcome per source, in order, each with its own
    error or fit, warnings and seconds (its own reading, pose search and closed-form stage; its share
    of the stages stepped together)."""
    prepare_worker(job.max_threads)
    outcomes: dict[int, Outcome] = {}
    observed: dict[int, Scan | tuple[NormalMap, Camera]] = {}
    landmarks: dict[int, tuple[Path, np.ndarray] | None] = {}
    for index, source in enumerate(sources):
        try:
            observed[index] = _read(job, source)
            landmarks[index] = _landmarks(job, source)     # None unless a register job names them
        except Exception as exc:  # noqa: BLE001 - this input's one line, the others go on
            observed.pop(index, None)
            outcomes[index] = Outcome(None, {}, one_line(exc), 0.0)
    order = sorted(observed)
    common = dict(stages=job.stages, device=job.device, threads=job.threads)
    try:
        model = _model(job.model, job.k)
        if job.command == "register":
            given = [None if landmarks[i] is None else landmarks[i][1] for i in order]
            together = register_many(model, [observed[i] for i in order], **common, fallback=job.fallback,
                                     landmarks=given if job.landmarks else None, **job.options)
        else:
            together = reconstruct_many(model, [observed[i][0] for i in order], [observed[i][1] for i in order],
                                        **common, **_render_options(job))
    except Exception as exc:  # noqa: BLE001 - a bad model or a bug: every fit of the group says so
        together = [FitOutcome(error=one_line(exc)) for _ in order]
    for index, fitted in zip(order, together):
        if fitted.fit is None:
            outcome = Outcome(None, {}, fitted.error, 0.0)
        else:
            outcome = _guarded(lambda: _with_landmarks(_fitted(job, model, observed[index], fitted.fit),
                                                       landmarks.get(index)))
            outcome.seconds = fitted.fit.seconds
        if fitted.warnings:
            outcome.summary["warnings"] = fitted.warnings
        outcomes[index] = outcome
    return [outcomes[index] for index in range(len(sources))]


def _guarded(work) -> Outcome:
    """``work()`` → (data, summary, extras) as an outcome, or its failure as the outcome's one-line error."""
    try:
        data, summary, extras = work()
        return Outcome(data, summary, None, 0.0, extras)
    except Exception as exc:  # noqa: BLE001 - a bug or an unforeseen input: recorded, the batch goes on
        return Outcome(None, {}, one_line(exc), 0.0)
