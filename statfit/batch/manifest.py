"""The batch's record: one JSON line per event in ``<out-dir>/manifest.jsonl``.

A ``run`` line opens each batch run (its settings, their key, and the inputs it covers); a ``fit``
line follows each finished input (its sha256, output, status ``done`` or ``failed``, the one-line
error, seconds, the fit's summary). Only the batch's own process appends, after the output is in
place, so a killed batch leaves at worst a truncated last line, which readers skip. A rerun skips
an input whose latest ``fit`` line is ``done`` with the same settings key and input digest and
whose output is still there, the same size.
"""
from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from statfit.errors import StatfitError

MANIFEST_NAME = "manifest.jsonl"
FSYNC_SECONDS = 1.0  # rows are flushed at once and made durable at most this long after


def settings_key(settings: dict[str, Any]) -> str:
    """A short stable digest of everything that decides an output."""
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]


def read_rows(path: Path) -> list[dict[str, Any]]:
    """Every readable line of a manifest (a line cut short by a kill is skipped)."""
    if not path.exists():
        return []
    rows = []
    with open(path, "rb") as handle:
        for line in handle:
            try:
                row = json.loads(line)
            except ValueError:
                continue
            if isinstance(row, dict) and row.get("event") in ("run", "fit"):
                rows.append(row)
    return rows


class Manifest:
    """Append-only writer of one manifest, held exclusively (a second batch writing into the same
    folder is refused)."""

    def __init__(self, path: Path):
        self.path = path
        try:
            self._handle = open(path, "ab")
        except OSError as exc:
            raise StatfitError(f"cannot write {path}: {exc.strerror}") from None
        self._lock()
        if self._handle.tell() > 0 and not self._ends_with_newline():
            self._handle.write(b"\n")  # the last line was cut short by a kill: start afresh
        self._synced = time.monotonic()

    def _lock(self) -> None:
        try:
            import fcntl
        except ImportError:  # not POSIX: no lock
            return
        try:
            fcntl.flock(self._handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            self._handle.close()
            raise StatfitError(f"another batch is writing to {self.path.parent}; wait for it or use another "
                               "--out-dir") from None

    def _ends_with_newline(self) -> bool:
        with open(self.path, "rb") as reader:
            reader.seek(-1, os.SEEK_END)
            return reader.read(1) == b"\n"

    def append(self, row: dict[str, Any]) -> None:
        self._handle.write(json.dumps(row).encode() + b"\n")
        self._handle.flush()
        if time.monotonic() - self._synced >= FSYNC_SECONDS:
            os.fsync(self._handle.fileno())
            self._synced = time.monotonic()

    def close(self) -> None:
        if not self._handle.closed:
            self._handle.flush()
            os.fsync(self._handle.fileno())
            self._handle.close()

    def __enter__(self) -> "Manifest":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def latest_fits(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The last ``fit`` row of every input."""
    return {row["input"]: row for row in rows if row["event"] == "fit"}


def is_current(row: dict[str, Any] | None, key: str, digest: str, out_dir: Path) -> bool:
    """Whether a ``fit`` row says its input is done with these settings, this input content, and
    its output still in place."""
    if row is None or row.get("status") != "done" or row.get("key") != key or row.get("sha256") != digest:
        return False
    output = out_dir / row.get("output", "")
    return output.is_file() and output.stat().st_size == row.get("bytes")


@dataclass
class BatchStatus:
    """Where the latest run stands: the inputs done, failed (with reasons) and still pending."""
    done: list[str] = field(default_factory=list)
    failed: list[tuple[str, str]] = field(default_factory=list)
    pending: list[str] = field(default_factory=list)
    settings: dict[str, Any] = field(default_factory=dict)


def batch_status(out_dir: Path) -> BatchStatus:
    """The status of the latest run recorded in ``out_dir``'s manifest."""
    path = out_dir / MANIFEST_NAME
    if not path.is_file():
        raise StatfitError(f"no batch in {out_dir} (no {MANIFEST_NAME})")
    rows = read_rows(path)
    runs = [row for row in rows if row["event"] == "run"]
    if not runs:
        raise StatfitError(f"{path} records no batch run")
    run = runs[-1]
    fits = latest_fits(rows)
    status = BatchStatus(settings=run.get("settings", {}))
    for source in run.get("inputs", []):
        row = fits.get(source)
        if row is not None and row.get("key") == run.get("key") and row.get("status") == "done":
            status.done.append(source)
        elif row is not None and row.get("key") == run.get("key") and row.get("status") == "failed":
            status.failed.append((source, row.get("error", "")))
        else:
            status.pending.append(source)
    return status
