"""Errors of a fitted mesh against a ground-truth mesh of the same topology."""
from __future__ import annotations

import numpy as np
import torch

from statfit.geometry.closest import ClosestPointQuery, border_vertices
from statfit.structures.frame import Frame
from statfit.renderer import Camera, rasterize
from statfit.structures.kdtree import kd_tree


def observed_vertices(vertices: np.ndarray, points: np.ndarray, radius: float | None = None) -> np.ndarray:
    """Boolean mask (N,): vertices within ``radius`` of an observed point; by default three times
    the points' median nearest-neighbour spacing."""
    return nearest_point_distance(vertices, points, radius)[1]


def nearest_point_distance(vertices: np.ndarray, points: np.ndarray, radius: float | None = None
                           ) -> tuple[np.ndarray, np.ndarray]:
    """(N,) distance of each vertex (N, 3) to the nearest of ``points`` (M, 3), and (N,) bool whether
    it lies within ``radius`` (default: three times the points' median nearest-neighbour spacing) —
    one KD-tree for both."""
    tree = kd_tree(points)
    if radius is None:
        spacing, _ = tree.query(points, k=2)
        radius = 3.0 * float(np.median(spacing[:, 1]))
    dist, _ = tree.query(vertices, k=1)
    return dist, dist <= radius


def visible_vertices(vertices: np.ndarray, faces: np.ndarray, camera: Camera, mask: np.ndarray | None = None
                     ) -> np.ndarray:
    """Boolean mask (N,): vertices of the triangles that cover a pixel of ``camera``'s image (and,
    with ``mask`` (H, W), a pixel on the mask): the part of the mesh a normal map observes."""
    fragments = rasterize(torch.as_tensor(vertices, dtype=torch.float64), torch.as_tensor(faces, dtype=torch.long),
                          camera)
    seen = fragments.face if mask is None else fragments.face[torch.as_tensor(mask).reshape(-1)[fragments.pixel]]
    visible = np.zeros(len(vertices), dtype=bool)
    visible[faces[np.unique(seen.numpy())].reshape(-1)] = True
    return visible


# A mesh whose surface, summed, faces one way by more than this share of its area is of part of a
# subject (a face mask: ~0.45; heads cut at the neck: 0.06-0.18): render's `auto` silhouette is
# one-sided for it (docs/studies.md §18), and the pose search scores it from both sides (§37).
PARTIAL_FACING_SHARE = 0.3


def facing_share(vertices: np.ndarray, faces: np.ndarray) -> float:
    """|Σ area-weighted triangle normals| / total area of the mesh (vertices (N, 3), faces (F, 3)):
    0 for a closed surface, 0.5 for a hemisphere shell, 1 for a flat sheet. A face mask (the front
    of a face only) is ~0.45; heads cut at the neck, ~0.05–0.2."""
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    doubled = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])   # 2 · area · normal
    total = np.linalg.norm(doubled, axis=1).sum()
    return float(np.linalg.norm(doubled.sum(axis=0)) / total) if total > 0 else 0.0


def of_part_of_a_subject(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """Whether the mesh (vertices (N, 3), faces (F, 3)) is of part of a subject, as a face mask is: its
    surface faces one way by more than :data:`PARTIAL_FACING_SHARE` of its area (:func:`facing_share`)."""
    return facing_share(vertices, faces) > PARTIAL_FACING_SHARE


def _exact_closest(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray):
    """The query (12 candidate vertices a point, float64) and its closest surface points."""
    query = ClosestPointQuery(faces, len(vertices), k=12)
    return query, query(torch.as_tensor(vertices, dtype=torch.float64), torch.as_tensor(points, dtype=torch.float64))


def surface_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Distance of each of ``points`` (M, 3) to the surface (``vertices``, ``faces``), (M,)."""
    return _exact_closest(points, vertices, faces)[1].distance.numpy()


# A larger scan is measured (and drawn) through this many of its points.
MEASURED_POINTS = 50_000


def measured_points(points: np.ndarray, most: int = MEASURED_POINTS) -> np.ndarray:
    """At most ``most`` of ``points`` (M, 3), a fixed draw in their order: the same rows every time."""
    if len(points) <= most:
        return points
    return points[np.sort(np.random.default_rng(0).choice(len(points), most, replace=False))]


def inside_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, border_band: float = 0.0
                    ) -> np.ndarray:
    """:func:`surface_distance`, NaN where the nearest surface point lies on the surface's open
    boundary: the point lies beyond what the surface covers (a scan's shoulders past a head cut
    at the neck), so its distance says nothing of the fit. With ``border_band`` (the points' unit),
    NaN too where the nearest surface point lies within that distance of a boundary vertex: a
    mask's neck and shoulders lie just beyond its chin, and under it. (M,)"""
    query, hit = _exact_closest(points, vertices, faces)
    opposite_open = query.open_edges[hit.triangle]                  # (M, 3): edge opposite corner i
    beyond = (opposite_open & (hit.barycentric < 1e-6)).any(dim=1).numpy()
    if border_band > 0 and (border := border_vertices(query.open_edges.numpy(), faces)).size:
        nearest = np.einsum("mi,mij->mj", hit.barycentric.numpy(), vertices[faces[hit.triangle.numpy()]])
        to_border, _ = kd_tree(vertices[border]).query(nearest, distance_upper_bound=border_band)
        beyond |= to_border < border_band
    return np.where(beyond, np.nan, hit.distance.numpy())


def _summary(values: np.ndarray, scale: float) -> dict[str, float]:
    if values.size == 0:
        return {"count": 0, "mean": float("nan"), "median": float("nan"), "max": float("nan"), "mean_rel": float("nan")}
    return {"count": int(values.size), "mean": float(values.mean()), "median": float(np.median(values)),
            "max": float(values.max()), "mean_rel": float(values.mean() / scale)}


def evaluate(fit: np.ndarray, gt: np.ndarray, faces: np.ndarray, observed: np.ndarray | None = None,
             region: np.ndarray | None = None, off_span: np.ndarray | None = None) -> dict:
    """Per-vertex errors ‖fit − gt‖ over all / observed / unobserved vertices, plus, on observed
    vertices, the distance of the ground truth to the fitted *surface*. ``mean_rel`` divides by
    the ground truth's RMS radius (unit-free). ``region`` (N,) bool restricts every summary to
    those vertices. ``off_span`` (N,), each fitted vertex's distance from the model's span (the fit
    PLY's field): the errors split into its quartiles, ``off_span_q1`` (the vertices closest to the
    span) to ``off_span_q4``, with the quartiles' edges in ``off_span_edges``."""
    scale = Frame.of(gt).scale
    err = np.linalg.norm(fit - gt, axis=1)
    inside = np.ones(len(gt), dtype=bool) if region is None else region
    report = {"scale": scale, "all": _summary(err[inside], scale)}
    if observed is not None:
        report["observed"] = _summary(err[observed & inside], scale)
        report["unobserved"] = _summary(err[~observed & inside], scale)
        report["observed_surface"] = _summary(surface_distance(gt[observed & inside], fit, faces), scale)
    if off_span is not None:
        report.update(off_span_quartiles(err[inside], np.asarray(off_span, dtype=np.float64)[inside], scale))
    return report


def off_span_quartiles(err: np.ndarray, off_span: np.ndarray, scale: float) -> dict:
    """Errors (M,) summarised over the quarters of the vertices ranked by ``off_span`` (M,),
    ``off_span_q1`` … ``q4`` (ties ranked in vertex order), and ``off_span_edges`` (5,): min, the
    quartiles, max of ``off_span``."""
    if err.size == 0:
        return {}
    rank = np.empty(err.size, dtype=np.int64)
    rank[np.argsort(off_span, kind="stable")] = np.arange(err.size)
    quarter = 4 * rank // err.size                                     # (M,) in 0..3
    report = {f"off_span_q{q + 1}": _summary(err[quarter == q], scale) for q in range(4)}
    report["off_span_edges"] = np.quantile(off_span, [0.0, 0.25, 0.5, 0.75, 1.0]).tolist()
    return report
