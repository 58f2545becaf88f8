"""Where a registration's paths part for a nudge (docs/studies.md §29, "a first probe"): three of §29's
cases that a 1e-4 mm nudge of the seen points moved most, each fitted as given and nudged, with the
fit's pre-alignment and its vertices at every snapshot compared (mm).

    python studies/register_pose_probe.py            # ~1 min
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import cross_family_landmarks as protocol  # noqa: E402
from adaptive_choice import single_threaded  # noqa: E402
from register_sensitivity import NUDGE_MM  # noqa: E402

CASES = (("ict", "ict-mask", 1, "right"), ("ict", "makehuman", 1, "lower"), ("ict-mask", "ict-mask", 0, "left"))


def fits(case: tuple) -> list:
    """The default's fit of ``case`` (people, model, seed, half) as given and nudged, each with its
    snapshots {iteration: vertices}."""
    import statfit
    from families import landmarked_model
    from statfit.structures.scan import Scan

    people, family, seed, half = case
    data = protocol.case_data(people, seed, half)
    model = landmarked_model(family)
    out = []
    for nudge in (0.0, NUDGE_MM):
        points = data["seen"].points + np.random.default_rng(1).standard_normal(data["seen"].points.shape) * nudge
        snapshots: dict[int, np.ndarray] = {}
        fit = statfit.register(model, Scan(points, data["seen"].normals), "default", landmarks=data["landmarks"],
                               threads=1, on_snapshot=lambda it, v: snapshots.__setitem__(it, v.copy()))
        out.append((fit, snapshots))
    return out


def main() -> None:
    single_threaded()
    for case in CASES:
        (given, given_snaps), (nudged, nudged_snaps) = fits(case)
        rotation = np.abs(np.asarray(given.transform.rotation) - np.asarray(nudged.transform.rotation)).max()
        shift = np.abs(np.asarray(given.transform.translation) - np.asarray(nudged.transform.translation)).max()
        common = sorted(set(given_snaps) & set(nudged_snaps))
        apart = [float(np.linalg.norm(given_snaps[it] - nudged_snaps[it], axis=1).mean()) for it in common]
        final = float(np.linalg.norm(given.vertices - nudged.vertices, axis=1).mean())
        used = [bool(fit.fallback and fit.fallback["used"]) for fit in (given, nudged)]
        print(f"{'/'.join(map(str, case))}: pre-alignment apart by {shift:.3g} mm and {rotation:.2g} in rotation; "
              f"vertices apart {apart[0]:.3g} mm at the first snapshot, {final:.3g} mm at the end; "
              f"fell back (given, nudged): {used}")


if __name__ == "__main__":
    main()
