"""Stand-ins for a fit, importable by spawned batch workers: copy the input, or misbehave by name."""
from __future__ import annotations

import os
import time
from pathlib import Path

from statfit.batch.fits import FitJob, Outcome


def copy_or_misbehave(job: FitJob, source: str) -> Outcome:
    """``crash*`` kills its worker, ``hang*`` sleeps for an hour, ``bad*`` fails, ``slow*`` takes half a
    second; all but the first three are copied."""
    name = Path(source).stem
    if name.startswith("crash"):
        os._exit(3)
    if name.startswith("hang"):
        time.sleep(3600)
    if name.startswith("slow"):
        time.sleep(0.5)
    if name.startswith("bad"):
        return Outcome(None, {}, f"{name} is bad", 0.0)
    return Outcome(Path(source).read_bytes(), {"worker": os.getpid()}, None, 0.0)


def copy_or_misbehave_together(job: FitJob, sources: list[str]) -> list[Outcome]:
    """:func:`copy_or_misbehave` for a group of inputs fitted in one program: one that crashes or
    hangs takes the whole group with it."""
    for source in sources:
        if Path(source).stem.startswith(("crash", "hang")):
            copy_or_misbehave(job, source)
    outcomes = [copy_or_misbehave(job, source) for source in sources]
    for outcome in outcomes:
        outcome.summary["group"] = len(sources)
    return outcomes
