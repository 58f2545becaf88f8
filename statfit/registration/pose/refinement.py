"""Steps 4 and 5 of the pose search: the best poses refined against the mean and its first modes,
then polished by Gauss–Newton on a rigid pose and every coefficient at once."""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from statfit.core.gauss_newton import fit_coefficients, mode_directions
from statfit.geometry.align import Similarity, compose
from statfit.model.statmodel import StatModel
from statfit.objectives.scan import ScanObjective
from statfit.registration.pose.hypotheses import Poses
from statfit.registration.pose.icp import KEEP, Matcher, trimmed_icp
from statfit.registration.pose.scoring import POLISH_TOLERANCE, score_poses
from statfit.structures.frame import Frame

ROUNDS = 15
REFINE_ROUNDS = 2
POLISH_ITERATIONS = 12
# A polish told to settle goes on past POLISH_ITERATIONS while its last pose step moved the model more
# than SETTLED (RMS radii: ICT 0.09 mm), up to SETTLE_MOST steps in all. Under heavy clutter (hair,
# neck and shoulders two to one) the pose can still slide ~1 mm a step at step 12: one of ICT's own
# people ended 14.6 mm up into the hair (docs/studies.md §41). A clean scan of the model's own people has
# settled by then (steps of 0.0002–0.0006) and stops at 12 as before, to the bit.
# It also goes on while its last step lowered the polish's objective (mean squared robust residual and
# prior, re-evaluated on the new closest points) by more than SETTLE_DROP of it. The clutter rule leaves
# out the points the model is not yet near, and they come back one by one as it nears them: the pose
# then creeps by under SETTLED a step while the objective still falls by 1–7% a step. MakeHuman face
# samples 6 and 20, polished from their true poses, stopped 3.4 and 3.3 mm off that way (their landmarks)
# and reach 0.7 and 0.2 mm in 60–70 steps (docs/studies.md §48).
SETTLED = 1e-3
SETTLE_DROP = 0.01
SETTLE_MOST = 100
POLISH_NOISE = 0.01        # the polish's prior (docs/method.md, "Real scans": 0.02 and 0.04 turn better on
                           # ICT and move worse on the embedded head)


def refine_with_first_modes(matcher: Matcher, mean: np.ndarray, basis_t: torch.Tensor, std: torch.Tensor,
                            points: np.ndarray, normals: np.ndarray, start: Similarity, bounds: tuple[float, float]
                            ) -> tuple[Similarity, float, float]:
    """``start`` refined against the mean plus its first modes (``basis_t`` (K, 3N) orthonormal,
    ``std`` (K,) in the unit frame): trimmed ICP and a Gauss–Newton coefficient solve, alternated.
    Returns the pose (model unit frame → scan unit frame), its score and matched share, scored on
    the shape fitted."""
    poses = Poses.of(start)
    shape = mean
    for _ in range(REFINE_ROUNDS):
        poses = trimmed_icp(matcher, points, normals, poses, ROUNDS // 2, bounds)
        local = torch.as_tensor(poses.to_model(points)[0])
        objective = ScanObjective(local, matcher.query, trim=1 - KEEP)
        fitted = fit_coefficients(torch.as_tensor(mean), basis_t, std, objective, torch.as_tensor(shape), 8,
                                  noise=0.05, levels=1)
        shape = fitted.vertices.numpy()
        matcher.set_shape(shape)
    score, matched = score_poses(matcher, points, normals, poses)
    matcher.set_shape(mean)
    return poses.pick(0), float(score[0]), float(matched[0])


def polish_pose(matcher: Matcher, mean: np.ndarray, directions: torch.Tensor, points: np.ndarray,
                normals: np.ndarray, start: Similarity, move: bool = True, region: np.ndarray | None = None,
                used: np.ndarray | None = None, settle: bool = False) -> tuple[Similarity, float, float, np.ndarray]:
    """Gauss–Newton on a rigid pose and every coefficient at once (``directions`` (N, 3, K): the
    modes times their standard deviations, :func:`scaled_modes`): the fit's own robust
    point-to-plane residuals, a Gaussian prior on the coefficients only, the pose updated by a small
    rigid motion of the scan points each step. The scale is the units' (``start``'s scale is
    dropped, keeping the scan's centroid in place): a person's size is the model's to explain, by
    its modes and under its prior; a free scale would trade against them at no cost. ``move`` False
    holds the pose; ``region`` (F,) bool: only points attached to these
    triangles are fitted; ``used`` (M,) bool: only these points are fitted (every point is scored);
    ``settle``: go on past POLISH_ITERATIONS while the pose still moves (SETTLED) or the objective
    still falls (SETTLE_DROP), up to SETTLE_MOST steps.
    Returns the pose (model unit frame → scan unit frame), its score (POLISH_TOLERANCE), matched
    share and the coefficients (K,) in standard deviations."""
    middle = start.inverse_apply(points).mean(axis=0)
    start = Similarity(1.0, start.rotation, start.apply(middle) - start.rotation @ middle)
    k = directions.shape[-1]
    coefficients = torch.zeros(k, dtype=torch.float64)
    moved_by = np.inf       # the last step's largest rotation (radians) or translation (RMS radii)
    before = np.inf         # the objective before the last step
    pose, mean_t = start, torch.as_tensor(mean)
    fitted, fitted_normals = (points, normals) if used is None else (points[used], normals[used])
    region_faces = None if region is None else torch.as_tensor(region)
    for iteration in range(SETTLE_MOST if settle and move else POLISH_ITERATIONS):
        local = torch.as_tensor(pose.inverse_apply(fitted))
        objective = ScanObjective(local, matcher.query, trim=0.05,
                                  normals=torch.as_tensor(fitted_normals @ pose.rotation), clutter=True,
                                  region_faces=region_faces)
        x = mean_t + directions @ coefficients
        objective.refresh(x)
        if objective.kept < 10:     # nothing left to say where to go (e.g. no point on the region): stay
            break
        residuals = objective.residuals(x)
        count = max(residuals.numel(), 1)
        value = (float(residuals.square().sum()) + POLISH_NOISE**2 * float(coefficients.square().sum())) / count
        fell_by = (before - value) / before if 0 < before < np.inf else np.inf     # the last step's, a share
        if iteration >= POLISH_ITERATIONS and moved_by <= SETTLED and fell_by <= SETTLE_DROP:
            break
        before = value
        jacobian = objective.jacobian(directions)
        centre = local.mean(dim=0)
        if move:
            jacobian = torch.cat([jacobian, objective.pose_jacobian(centre)[:, :6]], dim=1)
        prior = torch.zeros(jacobian.shape[1], dtype=torch.float64)
        prior[:k] = POLISH_NOISE**2 / count
        lhs = jacobian.T @ jacobian / count
        lhs = lhs + torch.diag(prior + 1e-12 * float(lhs.diagonal().mean()))
        rhs = jacobian.T @ residuals / count
        rhs[:k] += prior[:k] * coefficients
        step = -torch.linalg.solve(lhs, rhs).numpy()
        coefficients = coefficients + torch.as_tensor(step[:k])
        if move:
            rotation = Rotation.from_rotvec(step[k:k + 3]).as_matrix()
            c = centre.numpy()
            moved = c + step[k + 3:] - rotation @ c          # the scan points' motion: p ↦ R p + moved
            pose = compose(pose, Similarity(1.0, rotation.T, -rotation.T @ moved))
            moved_by = float(max(np.linalg.norm(step[k:k + 3]), np.linalg.norm(step[k + 3:])))
    shape = (mean_t + directions @ coefficients).numpy()
    matcher.set_shape(shape)
    poses = Poses.of(pose)
    score, matched = score_poses(matcher, points, normals, poses, POLISH_TOLERANCE)
    matcher.set_shape(mean)
    return pose, float(score[0]), float(matched[0]), coefficients.numpy()


def scaled_modes(model: StatModel, frame: Frame) -> torch.Tensor:
    """Every mode scaled by its standard deviation in the model's unit frame, vertex-major: (N, 3, K)."""
    basis_t = torch.as_tensor(np.ascontiguousarray(model.basis.T))
    return mode_directions(basis_t, torch.as_tensor(model.std / frame.scale))
