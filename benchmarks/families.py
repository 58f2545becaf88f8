"""Model families built from the open data, and people drawn from each: the cross-family cases
(issue 37; docs/studies.md §17).

- ``ict``: the ICT-FaceKit head, 11,248 vertices, 100 identity modes, centimetres.
- ``ict-mask``: ICT's face geometry alone (the front of the face, as BFM 2017 and most
  scanner-built models are), decimated to about 3,000 vertices, millimetres.
- ``makehuman``: the head of a MakeHuman body model (PCA of 3,000 random bodies, 200 modes, the
  head region cut out, its first 100 modes), 4,284 vertices, metres: another population, topology
  and resolution.
- ``embedded``: statfit's embedded synthetic head (4,842 vertices, 50 modes).
- ``makehuman-face`` (a check family, not in :data:`FAMILIES`): the front of MakeHuman's head model
  (its vertices less than 1 cm behind or below its hindmost and lowest landmark: a face mask cut
  from a body model, as one cut from SMPL-X would be), millimetres; its people are MakeHuman's, cut
  the same way.

People: ICT's are an identity sample plus an expression the identity model lacks (weight 0.5–1);
ICT-mask people are the same, on the mask's vertices; MakeHuman's are held-out bodies (asymmetric,
with expressions, older: outside the MakeHuman model) cut to the head; the embedded head's are model
samples. A person is a mesh of their family's topology in their family's units.

Landmarks (the 68 of the iBUG / Multi-PIE scheme) for the three real families
(:func:`landmarked_model`, :func:`person_landmarks`): ICT's own; the mask's, ICT's carried through the
cut to the nearest kept vertex (its people's: the ICT person's landmark vertices, exact); MakeHuman's,
transferred once from ICT by statfit itself: ICT's model registered to MakeHuman's mean head (the
default, no landmarks), each fitted landmark's nearest MakeHuman vertex (0.5–6 mm from it; mirror
partners symmetric to 0.8 mm on average). The embedded head has 10 landmarks of its own, so it
takes no part.

Built models and people are cached outside the repository (derived data never enters it):
``$STATFIT_STUDY_CACHE`` or ``~/.cache/statfit-studies``.
"""
from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path

import numpy as np

from common import ICT_EXPRESSIONS, ICT_MODEL, ROOT

FAMILIES = ("ict", "ict-mask", "makehuman", "embedded")
LANDMARKED = ("ict", "ict-mask", "makehuman")
CHECK_FAMILIES = ("makehuman-face",)
METRES_PER_UNIT = {"ict": 0.01, "ict-mask": 0.001, "makehuman": 1.0, "embedded": 1.0, "makehuman-face": 0.001}
MAKEHUMAN = ROOT.parent / "shared" / "data" / "makehuman"
MASK_VERTICES = 3000
MAKEHUMAN_SAMPLES, MAKEHUMAN_BODY_MODES, MAKEHUMAN_HEAD_MODES = 3000, 200, 100


def cache_dir() -> Path:
    folder = Path(os.environ.get("STATFIT_STUDY_CACHE", Path.home() / ".cache" / "statfit-studies"))
    folder.mkdir(parents=True, exist_ok=True)
    return folder


@lru_cache(maxsize=1)
def _ict_full():
    from statfit.model.statmodel import load_model, with_landmarks, with_regions

    with np.load(ICT_MODEL) as raw:
        face, landmarks = np.arange(int(raw["face_vertex_count"])), raw["landmarks68"].astype(np.int64)
    return with_landmarks(with_regions(load_model(ICT_MODEL), {"face": face}), landmarks)


@lru_cache(maxsize=1)
def _mask_vertices() -> np.ndarray:
    """The ICT vertices the mask keeps, in the mask's order."""
    from scipy.spatial import cKDTree

    distance, index = cKDTree(_ict_full().template).query(family_model("ict-mask").template / 10.0)
    assert distance.max() < 1e-9, "the mask's vertices are the ICT head's"
    return index


@lru_cache(maxsize=None)
def family_model(name: str):
    """The family's model (a :class:`statfit.model.statmodel.StatModel`), built once and cached."""
    from statfit.model.cut import decimated, region_part, rescaled, vertex_subset
    from statfit.model.statmodel import default_model_path, load_model, save_model

    if name == "ict":
        return _ict_full()
    if name == "embedded":
        return load_model(default_model_path())
    cached = cache_dir() / f"{name}.npz"
    if not cached.is_file():
        if name == "ict-mask":
            model = rescaled(decimated(region_part(_ict_full(), "face"), MASK_VERTICES), 10.0)
        elif name == "makehuman-face":
            model = rescaled(vertex_subset(landmarked_model("makehuman"), _makehuman_face_vertices(),
                                           nearest_landmarks=True), 1000.0)
        elif name == "makehuman":
            space = _makehuman_space()
            from statfit.model.importers.makehuman_shapes import body_regions, build_body_model

            body = build_body_model(space, MAKEHUMAN_BODY_MODES, MAKEHUMAN_SAMPLES, 0, body_regions(space)).model
            model = region_part(body, "head").truncated(MAKEHUMAN_HEAD_MODES)
        else:
            raise ValueError(f"unknown family {name!r}; choose one of {', '.join(FAMILIES)}")
        save_model(model, cached)
    return load_model(cached)


@lru_cache(maxsize=1)
def _makehuman_space():
    from statfit.model.importers.makehuman import read_makehuman
    from statfit.model.importers.makehuman_shapes import BodySpace

    return BodySpace(read_makehuman(MAKEHUMAN))


def _makehuman_face_vertices() -> np.ndarray:
    """The MakeHuman head model's vertices the face check family keeps (module docstring)."""
    model = landmarked_model("makehuman")
    template, landmarks = model.template, model.template[model.landmarks]
    ahead = template[:, 2] > landmarks[:, 2].min() - 0.01
    above = template[:, 1] > landmarks[:, 1].min() - 0.01
    return np.flatnonzero(ahead & above)


def _makehuman_head_vertices() -> np.ndarray:
    """The body vertices the MakeHuman head model keeps (the head region on whole triangles)."""
    cached = cache_dir() / "makehuman-head-vertices.npy"
    if not cached.is_file():
        from statfit.model.importers.makehuman_shapes import body_regions

        space = _makehuman_space()
        inside = np.zeros(len(space.data.vertices), dtype=bool)
        inside[body_regions(space)["head"]] = True
        np.save(cached, np.unique(space.data.faces[inside[space.data.faces].all(axis=1)]))
    return np.load(cached)


def person(family: str, seed: int) -> np.ndarray:
    """Vertices (N, 3) of person ``seed`` of ``family``, in the family's topology and units."""
    rng = np.random.default_rng(7000 + seed)
    if family in ("ict", "ict-mask"):
        from statfit.synth.sample import load_delta

        with np.load(ICT_EXPRESSIONS) as data:
            names = [str(n) for n in data["names"]]
        model = _ict_full()
        shape = model.sample(rng) + rng.uniform(0.5, 1.0) * load_delta(str(ICT_EXPRESSIONS),
                                                                       names[rng.integers(len(names))])
        return shape if family == "ict" else 10.0 * shape[_mask_vertices()]
    if family == "makehuman":
        cached = cache_dir() / f"makehuman-person-{seed}.npy"
        if not cached.is_file():
            space = _makehuman_space()
            body = space.shapes(space.weights(rng, 1, "held_out"))[0]
            np.save(cached, body[_makehuman_head_vertices()])
        return np.load(cached)
    if family == "embedded":
        return family_model("embedded").sample(rng)
    if family == "makehuman-face":
        return 1000.0 * person("makehuman", seed)[_makehuman_face_vertices()]
    raise ValueError(f"unknown family {family!r}; choose one of {', '.join(FAMILIES)}")


def build_all(families: list[str], people: int) -> None:
    """Build and cache the families' models and their first ``people`` people (before a study's
    workers start, so no two build the same one)."""
    for family in families:
        family_model(family)
        for seed in range(people):
            person(family, seed)


def _makehuman_landmarks() -> np.ndarray:
    """(68,) MakeHuman head-model vertex indices of ICT's landmarks, transferred once (module docstring)."""
    cached = cache_dir() / "makehuman-landmarks.npy"
    if not cached.is_file():
        import torch
        from scipy.spatial import cKDTree

        from statfit.registration.job import register
        from statfit.structures.scan import Scan

        torch.set_num_threads(1)
        ict, head = _ict_full(), family_model("makehuman")
        fit = register(ict, Scan.from_mesh(head.template, head.faces), threads=1)
        np.save(cached, cKDTree(head.template).query(fit.vertices[ict.landmarks])[1])
    return np.load(cached)


def landmarked_model(name: str):
    """The family's model with its 68 landmarks (a family of :data:`LANDMARKED`)."""
    from statfit.model.statmodel import with_landmarks

    if name == "makehuman-face":
        return family_model(name)
    if name not in LANDMARKED:
        raise ValueError(f"family {name!r} has no 68 landmarks; choose one of {', '.join(LANDMARKED)}")
    model = family_model(name)
    return with_landmarks(model, _makehuman_landmarks()) if name == "makehuman" else model


def person_landmarks(family: str, seed: int) -> np.ndarray:
    """(68, 3) the true landmark positions of person ``seed`` of ``family``, in the family's units."""
    if family == "ict-mask":
        return 10.0 * person("ict", seed)[_ict_full().landmarks]
    if family == "makehuman-face":
        return 1000.0 * person_landmarks("makehuman", seed)
    return person(family, seed)[landmarked_model(family).landmarks]
