"""A scan as the fit sees it: points with unit normals.

A mesh scan's vertices crowd where the scanner looked straight on and thin out at grazing angles,
so its points are drawn from its triangles by area instead (a fit weighted by where the scanner
happened to look would lean that way); their normals are the triangles'. A point cloud's normals
are estimated from its nearest neighbours. Normals are oriented away from the scan's centroid, a
guess that holds for a convex object seen from outside: use them up to sign.

A point cloud far denser than a fit needs (a million points of a head) is fitted through a
subsample spread evenly over it by area, sized from the model (:meth:`Scan.thinned`,
:func:`spread_subsample`: a voxel grid whose size is searched for the count, the point nearest
each occupied voxel's centre); its normals are estimated on the subsample alone. The fit's time
and memory then no longer grow with the scan's size; scans of the usual size are fitted as they are.
"""
from __future__ import annotations

import numpy as np

from statfit.errors import StatfitError
from statfit.structures.kdtree import kd_tree

# Points drawn from a mesh scan: as many as it has vertices, within these bounds (a head is well
# covered by far fewer than the most; the fit's cost grows with the count).
MESH_SAMPLES = (1_000, 20_000)
# Neighbours whose spread gives a point cloud's normal.
NORMAL_NEIGHBOURS = 12
# A dense point cloud is fitted through a subsample spread over it (Scan.thinned) of about
# FIT_POINTS_PER_VERTEX points per model vertex (at least MESH_SAMPLES[0]): the fit's cost stops
# growing with the scan's size. Only above THIN_ABOVE times that and above MESH_SAMPLES[1] (what a
# mesh scan's draw gives at most), so a scan of the usual size is fitted exactly as it is. On the
# ICT head (11,248 vertices) a 1,000,000-point scan is fitted in about the time of a 4,300-point one
# and as accurately as through all its points (docs/benchmarks.md, "Big scans").
FIT_POINTS_PER_VERTEX = 1
THIN_ABOVE = 2
# Rounds of the voxel size's search, and how near the target count is near enough.
VOXEL_ROUNDS = 6
VOXEL_TOLERANCE = 0.1


class Scan:
    """``points`` (M, 3) and their unit ``normals`` (M, 3); a point cloud's normals are estimated
    when first asked for (a dense cloud thinned first never estimates them for every point)."""

    def __init__(self, points: np.ndarray, normals: np.ndarray | None = None):
        self.points = points
        self._normals = normals

    @property
    def normals(self) -> np.ndarray:
        if self._normals is None:
            self._normals = _outward(self.points, estimate_normals(self.points))
        return self._normals

    def __repr__(self) -> str:
        return f"Scan({len(self.points)} points)"

    @classmethod
    def from_points(cls, points: np.ndarray) -> "Scan":
        """A point cloud (M, 3), normals estimated (when first used)."""
        return cls(np.asarray(points, dtype=np.float64))

    def thinned(self, target: int) -> "Scan":
        """This scan, or for more than THIN_ABOVE × ``target`` points (and more than MESH_SAMPLES[1])
        a subsample of about ``target`` points spread over it (:func:`spread_subsample`), with
        their normals (a point cloud's estimated on the subsample alone)."""
        if len(self.points) <= max(THIN_ABOVE * target, MESH_SAMPLES[1]):
            return self
        kept, _ = spread_subsample(self.points, target)
        return Scan(self.points[kept], None if self._normals is None else self._normals[kept])

    @classmethod
    def from_mesh(cls, vertices: np.ndarray, faces: np.ndarray, seed: int = 0,
                  count: int | None = None) -> "Scan":
        """Points drawn uniformly by area from a triangle mesh (``count``: as many as it has
        vertices, within MESH_SAMPLES), with their triangles' normals; deterministic for ``seed``."""
        vertices, faces = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.min(initial=0) < 0 or faces.max(initial=0) >= len(vertices):
            raise StatfitError("the scan mesh's faces must be vertex index triples")
        a, b, c = (vertices[faces[:, i]] for i in range(3))
        cross = np.cross(b - a, c - a)
        area = np.linalg.norm(cross, axis=1)
        if not np.isfinite(area).all() or area.sum() <= 0:
            raise StatfitError("the scan mesh has no triangle of positive area")
        count = count or int(np.clip(len(vertices), *MESH_SAMPLES))
        rng = np.random.default_rng(seed)
        triangle = rng.choice(len(faces), size=count, p=area / area.sum())
        r1, r2 = np.sqrt(rng.random(count))[:, None], rng.random(count)[:, None]
        points = (1 - r1) * a[triangle] + r1 * (1 - r2) * b[triangle] + r1 * r2 * c[triangle]
        return cls(points, _outward(points, cross[triangle] / area[triangle, None]))


def estimate_normals(points: np.ndarray, neighbours: int = NORMAL_NEIGHBOURS) -> np.ndarray:
    """Unit normals (M, 3) of a point cloud (M, 3), unoriented: the direction of least spread of
    each point's ``neighbours`` nearest points."""
    k = min(neighbours, len(points))
    _, nearest = kd_tree(points).query(points, k=k)
    local = points[nearest.reshape(len(points), k)]
    local = local - local.mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("mki,mkj->mij", local, local))
    return vectors[:, :, 0]


def _outward(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """``normals`` (M, 3) flipped to point away from the points' centroid."""
    return normals * np.where(((points - points.mean(axis=0)) * normals).sum(axis=1) < 0, -1.0, 1.0)[:, None]


def sample_size(num_vertices: int) -> int:
    """The points a fit of a model with ``num_vertices`` vertices draws from a dense scan."""
    return max(MESH_SAMPLES[0], FIT_POINTS_PER_VERTEX * num_vertices)


def voxel_keys(points: np.ndarray, voxel: float) -> tuple[np.ndarray, int]:
    """(M,) one integer per cubic voxel of side ``voxel`` (from the points' lowest corner) that holds
    each point, and how many integers there can be."""
    cells = ((points - points.min(axis=0)) * (1.0 / voxel)).astype(np.int64)   # ≥ 0: truncation floors
    shape = cells.max(axis=0) + 1
    return (cells[:, 0] * shape[1] + cells[:, 1]) * shape[2] + cells[:, 2], int(np.prod(shape))


def _labels(keys: np.ndarray, size: int) -> tuple[np.ndarray, int]:
    """``keys`` as labels 0 … V−1 of the V distinct ones (a count if their range is small, else a sort)."""
    if size <= 8 * len(keys) + 1024:
        present = np.bincount(keys, minlength=size) > 0
        return np.cumsum(present)[keys] - 1, int(present.sum())
    distinct, labels = np.unique(keys, return_inverse=True)
    return labels.reshape(-1), len(distinct)


def spread_subsample(points: np.ndarray, target: int) -> tuple[np.ndarray, float]:
    """About ``target`` of ``points`` (M, 3), spread evenly over them: on a cubic voxel grid, the
    point nearest each occupied voxel's centre. The voxel size is searched so that about ``target``
    voxels are occupied (a surface's count goes as 1 / size², whatever its units), so the
    subsample is even by area, whatever the scanner's density. Returns the kept points' indices
    in the scan's order and the voxel size; every point lies in a voxel with a kept point, so
    within √3 voxel sizes of one. Vectorised, no loop over points: O(M) per round."""
    extent = float(np.linalg.norm(np.ptp(points, axis=0)))
    voxel = max(extent, np.finfo(float).tiny) / np.sqrt(target)
    for _ in range(VOXEL_ROUNDS):
        occupied = _labels(*voxel_keys(points, voxel))[1]
        if abs(occupied - target) <= VOXEL_TOLERANCE * target:
            break
        voxel *= np.sqrt(occupied / target)
    labels, count = _labels(*voxel_keys(points, voxel))
    low = points.min(axis=0)
    offsets = (points - low) - (np.floor((points - low) * (1.0 / voxel)) + 0.5) * voxel
    distance = np.square(offsets).sum(axis=1)
    nearest = np.full(count, np.inf)
    np.minimum.at(nearest, labels, distance)
    winner = np.flatnonzero(distance == nearest[labels])
    first = np.full(count, len(points))
    np.minimum.at(first, labels[winner], winner)        # ties: the first in the scan's order
    return np.sort(first), voxel
