"""Bodies from MakeHuman's sliders, and the PCA body model learnt from them.

A body is the base mesh plus a weighted sum of targets. The weights come from sliders:

- **Macro sliders** (gender, age, muscle, weight, height, proportions, cup size, firmness, and the
  three race shares) weigh the ``macrodetails`` and breast corner targets as MakeHuman does: each
  slider's value gives piecewise-linear weights to its named corners (age: baby 0, child 0.1875,
  young 0.5, old 1; the others min 0, average 0.5, max 1; an unnamed average corner has no target),
  and a corner target's weight is the product of its corners' weights.
- **Local sliders** (``target.json``: one per decr/incr pair, per side where a slider has left and
  right, or a single 0..1 target) weigh one target by the slider's positive part and its opposite by
  the negative part.

Two distributions (docs/bodies.md says why the second is fair):

- ``train``: gender U(0, 1), age U(0.375, 0.875) (about 19 to 70 years), muscle, weight, height and
  proportions U(0.1, 0.9), cup size and firmness U(0, 1), race shares Dirichlet(1, 1, 1); every local
  slider N(0, 0.3²) clipped to its range, the left and right sides equal.
- ``held_out``: what the model never sees: two of muscle, weight, height and proportions in the tails
  [0, 0.1] ∪ [0.9, 1] and age up to 1 (90 years); left and right sides drawn independently; the
  ``asym`` targets (N(0, 0.5²) per left/right pair); the facial ``expression`` units (|N(0, 0.3²)|,
  shared out by the race shares).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from statfit.model.build import BuiltModel
from statfit.errors import StatfitError
from statfit.model.importers.makehuman import MakeHumanData
from statfit.model.statmodel import model_from_arrays

# Corners of each macro slider: (token in target names, slider value); "" is a corner without a target.
MACRO_CORNERS: dict[str, tuple[tuple[str, float], ...]] = {
    "gender": (("female", 0.0), ("male", 1.0)),
    "age": (("baby", 0.0), ("child", 0.1875), ("young", 0.5), ("old", 1.0)),
    "muscle": (("minmuscle", 0.0), ("averagemuscle", 0.5), ("maxmuscle", 1.0)),
    "weight": (("minweight", 0.0), ("averageweight", 0.5), ("maxweight", 1.0)),
    "height": (("minheight", 0.0), ("", 0.5), ("maxheight", 1.0)),
    "proportions": (("uncommonproportions", 0.0), ("", 0.5), ("idealproportions", 1.0)),
    "cupsize": (("mincup", 0.0), ("averagecup", 0.5), ("maxcup", 1.0)),
    "firmness": (("minfirmness", 0.0), ("averagefirmness", 0.5), ("maxfirmness", 1.0)),
}
RACES = ("african", "asian", "caucasian")
TRAIN_RANGES = {"gender": (0.0, 1.0), "age": (0.375, 0.875), "muscle": (0.1, 0.9), "weight": (0.1, 0.9),
                "height": (0.1, 0.9), "proportions": (0.1, 0.9), "cupsize": (0.0, 1.0), "firmness": (0.0, 1.0)}
TAILED = ("muscle", "weight", "height", "proportions")  # held out: two of these in the tails
LOCAL_STD = 0.3
ASYM_STD = 0.5
EXPRESSION_STD = 0.3
MOVED_SHARE = 0.25  # body_regions: a target's own vertices
HELD_OUT_CATEGORIES = ("asym", "expression")
Distribution = Literal["train", "held_out"]


@dataclass(frozen=True)
class LocalSlider:
    """One local slider: the target columns its positive and negative parts weigh (-1: none), its
    lowest value (-1, or 0 for a single target), and ``twin``: the index of its other side (or -1)."""

    positive: int
    negative: int
    lowest: float
    twin: int


class BodySpace:
    """The targets of a :class:`MakeHumanData` as one dense matrix, and the slider → weight rules.

    matrix: (T, 3N) float64 displacements in metres, vertex-major; names: (T,) target names."""

    def __init__(self, data: MakeHumanData):
        self.data = data
        self.names = sorted(data.targets)
        column = {name: i for i, name in enumerate(self.names)}
        n = len(data.vertices)
        self.matrix = np.zeros((len(self.names), 3 * n))
        for i, name in enumerate(self.names):
            target = data.targets[name]
            self.matrix[i].reshape(n, 3)[target.indices] += target.deltas
        self.macro = [(column[name], corners) for name in self.names
                      if (corners := _macro_corners(name)) is not None]
        self.local = _local_sliders(data.sliders, column)
        self.asym = _asym_pairs(self.names, column)
        expression = [name for name in self.names
                      if name.startswith("expression/units/") and name.split("/")[2] in RACES]
        units = sorted({name.rsplit("/", 1)[1] for name in expression})
        # (target column, race, expression unit) of each per-race expression target
        self.expression = [(column[name], RACES.index(name.split("/")[2]), units.index(name.rsplit("/", 1)[1]))
                           for name in expression]
        self.expression_units = len(units)
        if not self.macro:
            raise StatfitError("the MakeHuman folder has no macrodetails targets named as MakeHuman names them")

    def weights(self, rng: np.random.Generator, count: int, distribution: Distribution = "train") -> np.ndarray:
        """(count, T) target weights of ``count`` random bodies from ``distribution``."""
        if distribution not in ("train", "held_out"):
            raise StatfitError(f"unknown body distribution {distribution!r}; choose train or held_out")
        held_out = distribution == "held_out"
        values = {name: rng.uniform(*TRAIN_RANGES[name], size=count) for name in MACRO_CORNERS}
        if held_out:
            values["age"] = rng.uniform(0.375, 1.0, size=count)
            for row in range(count):
                for name in rng.choice(TAILED, size=2, replace=False):
                    tail = rng.uniform(0.0, 0.1)
                    values[name][row] = tail if rng.random() < 0.5 else 1.0 - tail
        races = rng.dirichlet(np.ones(len(RACES)), size=count)
        weights = np.zeros((count, len(self.names)))
        corner_weights = {name: _hat_weights(values[name], MACRO_CORNERS[name]) for name in MACRO_CORNERS}
        for col, corners in self.macro:
            product = np.ones(count)
            for kind, index in corners:
                product *= races[:, index] if kind == "race" else corner_weights[kind][:, index]
            weights[:, col] += product
        sliders = np.clip(rng.normal(0.0, LOCAL_STD, size=(count, len(self.local))),
                          [s.lowest for s in self.local], 1.0)
        if not held_out:  # a twin's value is its first side's
            for i, slider in enumerate(self.local):
                if 0 <= slider.twin < i:
                    sliders[:, i] = sliders[:, slider.twin]
        for i, slider in enumerate(self.local):
            _add_signed(weights, sliders[:, i], slider.positive, slider.negative)
        if held_out:
            for positive, negative in self.asym:
                _add_signed(weights, np.clip(rng.normal(0.0, ASYM_STD, size=count), -1, 1), positive, negative)
            strengths = np.clip(np.abs(rng.normal(0.0, EXPRESSION_STD, size=(count, self.expression_units))), 0.0, 1.0)
            for col, race, unit in self.expression:
                weights[:, col] += races[:, race] * strengths[:, unit]
        return weights

    def shapes(self, weights: np.ndarray) -> np.ndarray:
        """(count, N, 3) vertices of the bodies with target ``weights`` (count, T)."""
        flat = self.data.vertices.reshape(-1) + np.asarray(weights) @ self.matrix
        return flat.reshape(len(weights), -1, 3)


def build_body_model(space: BodySpace, k: int, samples: int, seed: int = 0,
                     regions: dict[str, np.ndarray] | None = None) -> BuiltModel:
    """The PCA model (first ``k`` modes) of ``samples`` bodies drawn from the ``train`` distribution
    with ``seed``; deterministic for a seed.

    Every body lies in the targets' span, so the sample matrix is ``W T`` (weights times targets):
    with ``Tᵀ = Q R`` the centred samples are ``(W_c Rᵀ) Qᵀ`` and their SVD is that of the small
    (samples × T) matrix ``W_c Rᵀ``, exact, without forming the (samples × 3N) matrix."""
    if samples < 2:
        raise StatfitError(f"building a model needs at least 2 samples, got {samples}")
    weights = space.weights(np.random.default_rng(seed), samples, "train")
    used = np.flatnonzero(np.abs(weights).max(axis=0) > 0)
    most = min(samples - 1, used.size)
    if not 1 <= k <= most:
        raise StatfitError(f"--k must be between 1 and {most} ({samples} samples of {used.size} targets)")
    mean_weights = weights[:, used].mean(axis=0)
    q, r = np.linalg.qr(space.matrix[used].T)
    left, singular, right = np.linalg.svd((weights[:, used] - mean_weights) @ r.T, full_matrices=False)
    del left
    std = singular / np.sqrt(samples - 1)
    directions = q @ right[:k].T  # (3N, k), orthonormal
    signs = np.sign(directions[np.abs(directions).argmax(axis=0), np.arange(k)])
    n = len(space.data.vertices)
    mean = space.data.vertices + (mean_weights @ space.matrix[used]).reshape(n, 3)
    shapedirs = (directions * signs * std[:k]).reshape(n, 3, k)
    model = model_from_arrays(mean, space.data.faces, shapedirs, regions=regions,
                              source=f"MakeHuman PCA of {samples} bodies (seed {seed})")
    variance = std**2
    return BuiltModel(model, np.cumsum(variance[:k]) / variance.sum())


def body_regions(space: BodySpace) -> dict[str, np.ndarray]:
    """Vertex regions of the body: ``left``, ``right`` (MakeHuman's groups) and ``head``, ``arms``,
    ``legs``, ``torso`` from the local targets' categories (a vertex a head target moves by over
    ``MOVED_SHARE`` of its largest move is the head's, else likewise the arms' or hands', else the
    legs' or feet'; the rest is the torso)."""
    n = len(space.data.vertices)
    owner = np.full(n, -1)
    parts = {"head": ("head", "ears", "eyes", "eyebrows", "nose", "mouth", "cheek", "chin", "forehead"),
             "arms": ("arms", "hands"), "legs": ("legs", "feet")}
    for rank, categories in reversed(list(enumerate(parts.values()))):
        moved = [_moved(space.data.targets[name]) for name in space.names if name.split("/")[0] in categories]
        if moved:
            owner[np.unique(np.concatenate(moved))] = rank
    regions = {name: np.flatnonzero(owner == rank) for rank, name in enumerate(parts)}
    regions["torso"] = np.flatnonzero(owner == -1)
    for side in ("Left", "Right"):
        if side in space.data.groups:
            regions[side.lower()] = space.data.groups[side]
    return {name: index for name, index in regions.items() if index.size}


def _moved(target) -> np.ndarray:
    """The vertices a target moves by more than ``MOVED_SHARE`` of its largest move."""
    lengths = np.linalg.norm(target.deltas, axis=1)
    return target.indices[lengths > MOVED_SHARE * lengths.max()]


def _hat_weights(values: np.ndarray, corners: tuple[tuple[str, float], ...]) -> np.ndarray:
    """(count, C) piecewise-linear weights of the corners at ``values`` (count,), clipped to the ends."""
    knots = np.array([value for _, value in corners])
    values = np.clip(values, knots[0], knots[-1])
    return np.stack([np.interp(values, knots, np.eye(len(knots))[i]) for i in range(len(knots))], axis=1)


_TOKENS = {token: (kind, i) for kind, corners in MACRO_CORNERS.items() for i, (token, _) in enumerate(corners) if token}
_TOKENS.update({race: ("race", i) for i, race in enumerate(RACES)})


def _macro_corners(name: str) -> list[tuple[str, int]] | None:
    """The (slider, corner) list of a corner target's name, or None for a target that is not one."""
    category, base = name.split("/")[0], name.rsplit("/", 1)[1]
    if category not in ("macrodetails", "breast"):
        return None
    tokens = [token for token in base.split("-") if token != "universal"]
    if not tokens or any(token not in _TOKENS for token in tokens):
        return None
    return [_TOKENS[token] for token in tokens]


def _local_sliders(sliders: dict, column: dict[str, int]) -> list[LocalSlider]:
    """The local sliders of ``target.json`` (categories not held out) whose targets exist."""
    found: list[LocalSlider] = []
    for category, spec in sliders.items():
        if category in HELD_OUT_CATEGORIES or not isinstance(spec, dict):
            continue
        for entry in spec.get("categories", []):
            names = entry.get("targets", [])
            opposites = entry.get("opposites")
            path = lambda target: column.get(f"{category}/{target}", -1) if target else -1  # noqa: E731
            if not opposites:
                if len(names) == 1 and path(names[0]) >= 0:
                    found.append(LocalSlider(path(names[0]), -1, 0.0, -1))
                continue
            sides = ("left", "right") if entry.get("has_left_and_right") else ("unsided",)
            pairs = [(path(opposites.get(f"positive-{side}")), path(opposites.get(f"negative-{side}"))) for side in sides]
            pairs = [pair for pair in pairs if max(pair) >= 0]
            first = len(found)
            for j, (positive, negative) in enumerate(pairs):
                found.append(LocalSlider(positive, negative, -1.0, first + 1 - j if len(pairs) == 2 else -1))
    return found


def _asym_pairs(names: list[str], column: dict[str, int]) -> list[tuple[int, int]]:
    """(right, left) target columns of each ``asym/<name>-l`` / ``-r`` pair."""
    return [(column[name[:-2] + "-r"], column[name]) for name in names
            if name.startswith("asym/") and name.endswith("-l") and name[:-2] + "-r" in column]


def _add_signed(weights: np.ndarray, values: np.ndarray, positive: int, negative: int) -> None:
    if positive >= 0:
        weights[:, positive] += np.maximum(values, 0.0)
    if negative >= 0:
        weights[:, negative] += np.maximum(-values, 0.0)
