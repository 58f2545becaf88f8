"""Where a registration's held-out guess is decided by nothing (docs/studies.md §30, after §29): every
third of §19's 72 cross-family held-out-half cases, each fitted with `register`'s default as given
and with its seen points nudged by 1e-4 mm (§29's nudge), under:

- ``shipped``: the default as it ships; the nudged case is also fitted with the pre-alignment of the
  fit as given forced on it (``forced``), which leaves only the fit after the pose to part the paths;
- ``constant``: the default before §30 (every step size constant), and its ``forced`` too;
- ``taper`` (at constant steps): the data term's 5% trim as a taper (weight 1 up to 3/4 of the
  trim's cut, linearly to 0 at the cut), in the pose search and the fit: the hard cut made smooth;
- ``fixed-levels`` (at constant steps): the closed-form stage's continuation run on a fixed schedule
  (6 Gauss–Newton steps per prior level, 12 at the last) instead of "until the data term improves by
  < 0.1%";
- ``settle``: every Adam stage's step size held for the first half of its iterations, then brought
  down linearly to 0 at its last (what ships does this for the ``laplacian`` stages alone);
- ``settle-polish``, ``polish-taper`` (as shipped): the pose search's polish (Gauss–Newton on the
  pose and every mode, POLISH_ITERATIONS steps) taking each of its last half's steps shortened the
  same way; or with its hard cuts as tapers centred on them: the clutter rules' (distance: 3 robust
  deviations, ±25%; normals: |cos| 0.5, ±0.1) and the trim's (±25%);
- ``edge-normals`` (as shipped, and its ``forced``): a point-to-plane residual whose scan point is
  closest to an edge or a vertex of the surface (where two or more triangles tie, and which one the
  closest-point query returns is a coin a nudge flips) takes the direction from that closest point
  to the scan point, signed as the attached triangle's normal, instead of that triangle's normal;
  in every Gauss–Newton solve (the pose's polish, the closed form, the hair test);
  ``edge-normals-everywhere``: the same normal also in the clutter rules' test of a point's normal
  against the surface's (the pose's polish always runs it);
- ``polish-30``, ``polish-30-edges``: what ships, with the pose's polish run for 30 Gauss–Newton
  steps instead of POLISH_ITERATIONS (12; by 30 its steps turn < 0.001°); and that with
  ``edge-normals-everywhere``.

``--accuracy VARIANT`` refits the cases of studies/default_fallback.py (§23's sets: §15, §12, §9, §8
in family; §19, §17 across families) under ``constant`` or ``edge-normals``, and sets them beside the
shipped default's rows there (which must have run with the code as shipped).

``--landmark-pose`` runs the probe of the pose polished with the landmarks as a term (one case, three
weights, the term on the pose and modes or on the pose alone) and prints what it does to the pose.

    python studies/register_instability.py                  # ~40 min on 2 cores
    python studies/register_instability.py --report
    python studies/register_instability.py --accuracy constant       # §19 and §17 only: ~5 min on 2 cores
    python studies/register_instability.py --accuracy edge-normals   # every set: ~8 min
    python studies/register_instability.py --landmark-pose  # ~10 s
"""
from __future__ import annotations

import argparse
import contextlib
import math
import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import cross_family_landmarks as protocol  # noqa: E402
from families import LANDMARKED  # noqa: E402
from register_sensitivity import NUDGE_MM  # noqa: E402
from study_runs import run_or_report  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "register_instability.json"
ACCURACY = ROOT / "studies" / "results" / "register_instability_accuracy.json"
SHIPPED = ROOT / "studies" / "results" / "default_fallback.json"
VARIANTS = ("shipped", "constant", "taper", "fixed-levels", "settle", "settle-polish", "polish-taper", "edge-normals",
            "edge-normals-everywhere", "polish-30", "polish-30-edges")
# The variants whose nudged case is also fitted with the given pose.
FORCED = ("shipped", "constant", "edge-normals", "edge-normals-everywhere", "polish-30", "polish-30-edges")
TAPER = 0.25          # the taper's width, as a share of the trim's cut
PER_LEVEL, LAST_LEVEL = 6, 12


def tapered_refresh(refresh):
    """ScanObjective.refresh with the quantile trim replaced by a taper; the residuals, Jacobians and
    value then weigh each point by it (rows scaled by √(w·M'/Σw), so a mean over the rows is Σ w r² / Σ w)."""
    from statfit.objectives.scan import masked_quantile

    def tapered(self, vertices):
        trim, self.trim = self.trim, 0.0
        try:
            attachment = refresh(self, vertices)          # the border, region and clutter rules only
        finally:
            self.trim = trim
        dist, counted = attachment.distance, self._keep
        weights = counted.to(dist.dtype)
        if trim > 0:
            cut = masked_quantile(dist, counted, 1.0 - trim)
            weights = weights * (cut - dist).div(TAPER * cut).clamp(0, 1)
        self._keep, total = weights > 0, weights.sum()
        self._mean_weights, self._grad_weights = (weights / total).view(-1, 1, 1), (2 * weights / total).view(-1, 1, 1)
        self._row_scale = (weights[self._keep] * self._keep.sum() / total).sqrt()
        return attachment
    return tapered


def taper_patches() -> list:
    import torch

    from statfit.objectives.scan import ScanObjective, _PointToSurface

    residuals, jacobian, pose_jacobian = ScanObjective.residuals, ScanObjective.jacobian, ScanObjective.pose_jacobian

    def value(self, vertices):
        if vertices.requires_grad and torch.is_grad_enabled():
            return {"data": _PointToSurface.apply(vertices, self)}
        squared = (self.points - self._attached(vertices)).square().sum(dim=1)
        return {"data": (squared * self._mean_weights.view(-1)).sum()}

    return [mock.patch.object(ScanObjective, "refresh", tapered_refresh(ScanObjective.refresh)),
            mock.patch.object(ScanObjective, "residuals", lambda self, v: residuals(self, v) * self._row_scale),
            mock.patch.object(ScanObjective, "jacobian", lambda self, d: jacobian(self, d) * self._row_scale[:, None]),
            mock.patch.object(ScanObjective, "pose_jacobian",
                              lambda self, c: pose_jacobian(self, c) * self._row_scale[:, None]),
            mock.patch.object(ScanObjective, "__call__", value)]


def polish_taper():
    """The polish's ScanObjective with its clutter rules and trim as tapers centred on their cuts."""
    from statfit.objectives import scan
    from statfit.registration.pose import refinement

    def above(value, cut, width):
        """1 from (1 + width) · cut up, 0 from (1 − width) · cut down, linear between."""
        return ((value - cut) / (2 * width * cut) + 0.5).clamp(0, 1)

    class Tapered(refinement.ScanObjective):
        def refresh(self, vertices):
            clutter, trim, self.clutter, self.trim = self.clutter, self.trim, False, 0.0
            try:
                attachment = super().refresh(vertices)       # the border and region rules only
            finally:
                self.clutter, self.trim = clutter, trim
            dist, base = attachment.distance, self._keep
            weights = base.to(dist.dtype)
            if clutter and self.scan_normals is not None:
                cosine = (self.normals * self.scan_normals).sum(dim=-1).abs()
                median = scan.masked_median(dist, base & (cosine >= scan.NORMAL_COSINE)).double()
                cut = (scan.OUTLIER_SIGMAS * 1.4826 * median).clamp_min(scan.FLOOR).to(dist.dtype)
                weights = weights * above(cosine, scan.NORMAL_COSINE, 0.2) * (1 - above(dist, cut, 0.25))
            if trim > 0:
                cut = scan.masked_quantile(dist, weights > 0, 1.0 - trim)
                weights = weights * (1 - above(dist, cut, 0.25))
            self._keep, total = weights > 0, weights.sum()
            self._mean_weights = (weights / total).view(-1, 1, 1)
            self._grad_weights = (2 * weights / total).view(-1, 1, 1)
            self._row_scale = (weights[self._keep] * self._keep.sum() / total).sqrt()
            return attachment

        def residuals(self, x):
            return super().residuals(x) * self._row_scale

        def jacobian(self, directions):
            return super().jacobian(directions) * self._row_scale[:, None]

        def pose_jacobian(self, centre):
            return super().pose_jacobian(centre) * self._row_scale[:, None]

    return [mock.patch.object(refinement, "ScanObjective", Tapered)]


def edge_normals(everywhere_too: bool = False) -> list:
    """ScanObjective's residuals, Jacobians and pose Jacobians with the offset's direction as the
    normal where a scan point's closest surface point lies on an edge or a vertex."""
    import torch

    from statfit.objectives.scan import ON_EDGE, ScanObjective, attached_normals

    def plane_normals(self) -> torch.Tensor:
        faces = self.normals
        offsets = self.points - self._attached(self._refreshed_at)
        length = offsets.norm(dim=-1, keepdim=True)
        direction = offsets / length.clamp_min(torch.finfo(offsets.dtype).tiny)
        direction = torch.where((direction * faces).sum(dim=-1, keepdim=True) < 0, -direction, direction)
        tied = (self.attachment.barycentric < ON_EDGE).any(dim=-1, keepdim=True) & (length > 1e-9)
        return torch.where(tied, direction, faces)

    def swapped(method):
        """``method`` run with ``normals`` reading the residuals' normals."""
        def run(self, *args):
            faces = self.normals
            self._normals = plane_normals(self)
            try:
                return method(self, *args)
            finally:
                self._normals = faces
        return run

    def everywhere(self) -> torch.Tensor:
        if self._normals is None:
            self._normals = attached_normals(self._refreshed_at, self._corner_ids)
            self._normals = plane_normals(self)
        return self._normals

    if everywhere_too:
        return [mock.patch.object(ScanObjective, "normals", property(everywhere))]
    return [mock.patch.object(ScanObjective, name, swapped(getattr(ScanObjective, name)))
            for name in ("residuals", "jacobian", "pose_jacobian")]


def fixed_levels(mean, basis_t, std, objective, x0, iterations, noise, levels=5, tolerance=None, first_iteration=0,
                 on_record=None, on_snapshot=None):
    """fit_coefficients with PER_LEVEL steps per prior level and LAST_LEVEL at the last, whatever the
    data term does (the shipped stage moves on when it improves by less than 0.1%)."""
    import torch

    from statfit.core.gauss_newton import SINGULAR_GUARD, CoefficientFit, mode_directions

    started = time.perf_counter()
    directions = mode_directions(basis_t, std).contiguous()
    coefficients = (torch.mv(basis_t, (x0 - mean).reshape(-1)) / std).double()
    eye = torch.eye(len(std), dtype=torch.float64)
    schedule = [noise * math.sqrt(10.0) ** level for level in reversed(range(max(1, levels)))]
    for step, sigma in enumerate([s for s in schedule[:-1] for _ in range(PER_LEVEL)] + [schedule[-1]] * LAST_LEVEL):
        x = mean + directions @ coefficients.to(mean.dtype)
        objective.refresh(x)
        r = objective.residuals(x).double()
        count = max(r.numel(), 1)
        if on_snapshot:
            on_snapshot(first_iteration + step, x)
        jac = objective.jacobian(directions).double()
        lhs = jac.T @ jac / count
        lhs = lhs + (sigma**2 / count + SINGULAR_GUARD * float(lhs.diagonal().mean())) * eye
        coefficients = coefficients - torch.linalg.solve(lhs, jac.T @ r / count + sigma**2 / count * coefficients)
    x = mean + directions @ coefficients.to(mean.dtype)
    return CoefficientFit(x, coefficients, {"data": float(objective(x)["data"])}, step + 1,
                          time.perf_counter() - started)


def settling(run_fit):
    """run_fit whose optimiser's step size is held for the first half of the stage's iterations, then
    brought down linearly to 0 at its last (a stage that settles itself left as it is)."""
    def settled(param, optimizer, objective, iterations, **kwargs):
        if getattr(optimizer, "settle", 0.0):
            return run_fit(param, optimizer, objective, iterations, **kwargs)
        sizes, step, taken = [group["lr"] for group in optimizer.param_groups], optimizer.step, [0]

        def scheduled(*args, **kw):
            share = min(1.0, 2.0 * (1.0 - taken[0] / max(iterations - 1, 1)))
            for group, size in zip(optimizer.param_groups, sizes):
                group["lr"] = size * share
            taken[0] += 1
            return step(*args, **kw)
        optimizer.step = scheduled
        return run_fit(param, optimizer, objective, iterations, **kwargs)
    return settled


def settled_polish(polish):
    """polish_pose whose Gauss–Newton steps are shortened by the settling share (the solve's result
    scaled: the polish's only solve)."""
    import torch

    from statfit.registration.pose.refinement import POLISH_ITERATIONS

    solve = torch.linalg.solve

    def polished(*args, **kwargs):
        taken = [0]

        def shortened(lhs, rhs):
            taken[0] += 1
            return solve(lhs, rhs) * min(1.0, (POLISH_ITERATIONS - taken[0] + 1) / (0.5 * POLISH_ITERATIONS))
        with mock.patch.object(torch.linalg, "solve", shortened):
            return polish(*args, **kwargs)
    return polished


def patches(variant: str) -> list:
    import statfit.core.stages as stages
    import statfit.registration.pose.refinement as refinement
    import statfit.registration.pose.search as search
    from statfit.core.optim import UniformAdam

    constant = [mock.patch.object(UniformAdam, "_share", lambda self, t: 1.0)]
    longer = [mock.patch.object(refinement, "POLISH_ITERATIONS", 30)]
    return {"shipped": [], "constant": constant, "taper": constant + taper_patches(),
            "fixed-levels": constant + [mock.patch.object(stages, "fit_coefficients", fixed_levels)],
            "settle": [mock.patch.object(stages, "run_fit", settling(stages.run_fit))],
            "settle-polish": [mock.patch.object(search, "polish_pose", settled_polish(search.polish_pose))],
            "polish-taper": polish_taper(), "edge-normals": edge_normals(),
            "edge-normals-everywhere": edge_normals(everywhere_too=True), "polish-30": longer,
            "polish-30-edges": longer + edge_normals(everywhere_too=True)}[variant]


def fit(people: str, model_family: str, seed: int, half: str, variant: str) -> dict:
    """One case under ``variant``: ``held`` as given, ``nudged``, and (shipped) ``forced``, the nudged
    fit with the given fit's pre-alignment."""
    import warnings

    import statfit
    import statfit.registration.posed as posed
    from adaptive_choice import single_threaded
    from cross_family import inside_distance
    from families import landmarked_model
    from statfit.structures.scan import Scan

    single_threaded()
    warnings.simplefilter("ignore")
    data, model = protocol.case_data(people, seed, half), landmarked_model(model_family)
    searched = posed.prealign

    def held(nudge: float, pose=None) -> tuple[float, tuple, bool]:
        points = data["seen"].points + np.random.default_rng(1).standard_normal(data["seen"].points.shape) * nudge
        found = {}

        def prealign(*args, **kwargs):
            found["pose"] = searched(*args, **kwargs) if pose is None else pose
            return found["pose"]
        with contextlib.ExitStack() as stack:
            for patch in [mock.patch.object(posed, "prealign", prealign), *patches(variant)]:
                stack.enter_context(patch)
            result = statfit.register(model, Scan(points, data["seen"].normals), "default",
                                      landmarks=data["landmarks"], threads=1)
        error = float(np.nanmean(inside_distance(data["held"], result.vertices, model.faces)))
        return error, found["pose"], bool(result.fallback and result.fallback["used"])

    given, pose, fell_back = held(0.0)
    nudged, _, nudged_fell_back = held(NUDGE_MM)
    row = {"people": people, "model": model_family, "seed": seed, "half": half, "variant": variant,
           "held": given, "nudged": nudged, "fell_back": [fell_back, nudged_fell_back]}
    return row | ({"forced": held(NUDGE_MM, pose)[0]} if variant in FORCED else {})


def runs() -> list[tuple]:
    from families import build_all, landmarked_model

    build_all(list(LANDMARKED), 2)
    for family in LANDMARKED:
        landmarked_model(family)
    cases = [(p, m, s, h) for p in LANDMARKED for m in LANDMARKED for s in range(2) for h in protocol.HALVES][::3]
    return [case + (variant,) for variant in VARIANTS for case in cases]


def report(rows: list[dict]) -> str:
    lines = ["| variant | cases | held, as given (mm) | held, nudged (mm) | mean \\|nudged ÷ given − 1\\| | "
             "moved by > 10% | fell back (given) |", "|---|---|---|---|---|---|---|"]
    for variant in VARIANTS:
        own = [r for r in rows if r["variant"] == variant]
        if not own:
            continue
        given, nudged = np.array([r["held"] for r in own]), np.array([r["nudged"] for r in own])
        moved = np.abs(nudged / given - 1)
        lines.append(f"| {variant} | {len(own)} | {given.mean():.3f} | {nudged.mean():.3f} | {moved.mean():.3f} | "
                     f"{int((moved > 0.1).sum())} | {sum(r['fell_back'][0] for r in own)} |")
        if variant in FORCED:
            forced = np.abs(np.array([r["forced"] for r in own]) / given - 1)
            lines.append(f"| {variant}, nudged with the given pose | {len(own)} | {given.mean():.3f} | "
                         f"{np.mean([r['forced'] for r in own]):.3f} | {forced.mean():.3f} | "
                         f"{int((forced > 0.1).sum())} | |")
    return "\n".join(lines)


def variant_case(variant: str, name: str, *key) -> dict:
    """default_fallback's case ``key`` of set ``name`` fitted under ``variant``."""
    from default_fallback import run_case

    with contextlib.ExitStack() as stack:
        for patch in patches(variant):
            stack.enter_context(patch)
        return {"variant": variant, **run_case(name, *key)}


def accuracy_key(row: dict) -> tuple:
    from default_fallback import row_key

    return row_key(row)


def accuracy_runs(variant: str) -> list[tuple]:
    import json

    sets = ("§19", "§17") if variant == "constant" else ("§15", "§12", "§9", "§8", "§19", "§17")
    return [(variant, *accuracy_key(r)) for r in json.loads(SHIPPED.read_text()) if r["set"] in sets]


def accuracy_report(rows: list[dict]) -> str:
    import json

    from default_fallback import ERROR

    shipped = {accuracy_key(r): r for r in json.loads(SHIPPED.read_text())}
    lines = ["| variant | set | cases | variant's error | shipped | ratio | fallback fired (shipped / variant) |",
             "|---|---|---|---|---|---|---|"]
    for variant in ("constant", "edge-normals"):
        for name, error in (*ERROR.items(), ("§8", "face_mm_0.0"), ("§8", "face_mm_0.5")):
            both = [(r, shipped[accuracy_key(r)]) for r in rows if r["variant"] == variant and r["set"] == name
                    and accuracy_key(r) in shipped and error in r and error in shipped[accuracy_key(r)]]
            if not both:
                continue
            fired = [sum(bool(x.get("fallback") and x["fallback"]["used"]) for x in side) for side in zip(*both)]
            mine, theirs = np.mean([a[error] for a, _ in both]), np.mean([b[error] for _, b in both])
            label = f"{name}, clutter {error[8:]}" if name == "§8" else name
            lines.append(f"| {variant} | {label} | {len(both)} | {mine:.4g} | {theirs:.4g} | {mine / theirs:.3f} | "
                         f"{fired[1]} / {fired[0]} |")
    return "\n".join(lines)


def landmark_pose_probe() -> None:
    """The pose polished with the landmarks as a Gauss–Newton term (robust, weight w per landmark
    against the scan's mean, as the fit weighs them), on the modes and the pose or on the pose alone:
    what it does to the landmarks it was given and to the held-out ones (ICT people, ICT's model,
    seed 0, left half). The landmarks ride along as the polish's last points, so they move with its
    pose; the scan term leaves them out and the landmark rows pull them to their model vertices."""
    import torch

    import statfit.registration.pose.refinement as refinement
    import statfit.registration.pose.search as search
    from adaptive_choice import single_threaded
    from families import landmarked_model
    from statfit.objectives.landmarks import ROBUST_SCALE
    from statfit.registration.prealign import landmark_alignment
    from statfit.structures.frame import Frame

    single_threaded()
    data, model = protocol.case_data("ict", 0, "left"), landmarked_model("ict")
    given = np.isfinite(data["landmarks"]).all(axis=1)
    vertices, count = model.landmarks[given], int(given.sum())
    start = landmark_alignment(model, data["landmarks"])
    centroid, frame = data["seen"].points.mean(axis=0), Frame.of(model.template)
    units = float(10.0 ** np.round(np.log10(start.scale)))
    targets = (data["landmarks"][given] - centroid) / (units * frame.scale)
    polish = search.polish_pose
    for weight, pose_only in ((0.0, False), (1.0, False), (10.0, False), (1.0, True), (10.0, True)):

        class PulledScan(refinement.ScanObjective):
            """The polish's scan term on all but the last ``count`` points, plus their landmark rows."""

            def refresh(self, x):
                attachment = super().refresh(x)
                self._keep[-count:] = False
                offset = self.points[-count:] - x[vertices]
                irls = ROBUST_SCALE**4 / (ROBUST_SCALE**2 + offset.square().sum(dim=1)).square()
                self.factor = (weight * int(self._keep.sum()) / count * irls).sqrt()[:, None]
                return attachment

            def residuals(self, x):
                offset = self.points[-count:] - x[vertices]
                return torch.cat([super().residuals(x), (self.factor * offset).reshape(-1)])

            def jacobian(self, directions):
                pulled = -(self.factor[:, :, None] * directions[vertices]).reshape(-1, directions.shape[-1])
                return torch.cat([super().jacobian(directions), torch.zeros_like(pulled) if pose_only else pulled])

            def pose_jacobian(self, centre):
                arm = self.points[-count:] - centre
                turn = torch.linalg.cross(torch.eye(3, dtype=arm.dtype)[None], arm[:, None, :].expand(-1, 3, 3))
                moved = torch.cat([turn.transpose(1, 2), torch.eye(3, dtype=arm.dtype).expand(count, 3, 3),
                                   torch.zeros(count, 3, 1, dtype=arm.dtype)], dim=2)
                return torch.cat([super().pose_jacobian(centre), (self.factor[:, :, None] * moved).reshape(-1, 7)])

        def with_landmarks(matcher, mean, directions, points, normals, pose, **kwargs):
            return polish(matcher, mean, directions, np.vstack([points, targets]),
                          np.vstack([normals, np.tile([0.0, 0.0, 1.0], (count, 1))]), pose, **kwargs)

        with mock.patch.object(refinement, "ScanObjective", PulledScan), \
                mock.patch.object(search, "polish_pose", with_landmarks):
            estimate = search.refine_pose(model, data["seen"], start)
        shape = model.template + (model.basis @ (estimate.coefficients * model.std)).reshape(-1, 3)
        placed = estimate.transform.apply(shape)
        seen = np.linalg.norm(placed[vertices] - data["landmarks"][given], axis=1).mean()
        held_out = data["held_landmarks"]
        held = np.linalg.norm(placed[model.landmarks[held_out]] - data["truth"][held_out], axis=1).mean()
        print(f"weight {weight:g}{' on the pose alone' if pose_only else ''}: given landmarks {seen:.2f} mm, "
              f"held-out landmarks {held:.2f} mm, coefficients' RMS {np.sqrt(np.mean(estimate.coefficients ** 2)):.2f}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--report", action="store_true", help="only print the table of the stored rows")
    parser.add_argument("--landmark-pose", action="store_true", help="run the landmark-pose probe and print it")
    parser.add_argument("--accuracy", choices=("constant", "edge-normals"),
                        help="refit §23's sets (default_fallback.py's) under this variant")
    args = parser.parse_args()
    if args.landmark_pose:
        landmark_pose_probe()
    elif args.accuracy:
        run_or_report(variant_case, [] if args.report else accuracy_runs(args.accuracy), ACCURACY, accuracy_report,
                      args.report, key=lambda r: (r["variant"], *accuracy_key(r)))
    else:
        run_or_report(fit, [] if args.report else runs(), RESULTS, report, args.report,
                      key=lambda r: (r["people"], r["model"], r["seed"], r["half"], r["variant"]))
