"""The pose search's second look (step 7, docs/studies.md §44): a second grid of starts only where
the first search's pose leaves doubt, its candidates competing with the first's."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from statfit.errors import StatfitError
from statfit.registration.pose import search
from statfit.registration.pose.hypotheses import HYPOTHESES, angle_between
from statfit.registration.pose.search import estimate_pose
from statfit.structures.scan import Scan
from statfit.synth.scanner import realistic_scan


def _scan(model, seed: int):
    rng = np.random.default_rng(seed)
    made = realistic_scan(model.sample(rng), model.faces, rng, yaw_deg=rng.uniform(-40, 40), clutter=0.0, units="mm")
    return made, Scan.from_mesh(made.vertices, made.faces)


def _searches(monkeypatch) -> list[int]:
    """The number of starts of each grid the searches run (a list filled as they run)."""
    grids: list[int] = []
    candidates = search.Search.candidates

    def counted(self, rotations):
        grids.append(len(rotations))
        return candidates(self, rotations)

    monkeypatch.setattr(search.Search, "candidates", counted)
    return grids


def test_a_clear_pose_is_not_looked_for_again(embedded_model, monkeypatch):
    """A clean scan of one of the model's people: one grid, the pose within a few degrees."""
    torch.set_num_threads(1)
    grids = _searches(monkeypatch)
    made, scan = _scan(embedded_model, 3)
    estimate = estimate_pose(embedded_model, scan, threads=1)
    assert grids == [len(HYPOTHESES)]
    assert not estimate.ambiguous
    assert angle_between(estimate.transform.rotation, made.transform.rotation) < 3.0


@pytest.mark.parametrize("looks_again", [True, False])
def test_the_second_grid_finds_the_pose_the_first_cannot(embedded_model, monkeypatch, looks_again):
    """The first grid stripped of every start within 75° of the true pose misses it, and its pose
    leaves doubt; the second grid (here the whole group) then finds it. With a second grid as blind as
    the first, the search ends refused or wrong: the second look is what found it."""
    torch.set_num_threads(1)
    made, scan = _scan(embedded_model, 4)
    far = np.array([angle_between(rotation, made.transform.rotation) > 75.0 for rotation in HYPOTHESES])
    monkeypatch.setattr(search, "HYPOTHESES", HYPOTHESES[far])
    monkeypatch.setattr(search, "SECOND_HYPOTHESES", HYPOTHESES if looks_again else HYPOTHESES[far])
    grids = _searches(monkeypatch)
    try:
        angle = angle_between(estimate_pose(embedded_model, scan, threads=1).transform.rotation,
                              made.transform.rotation)
    except StatfitError:
        angle = np.inf
    assert grids == [far.sum(), len(HYPOTHESES) if looks_again else far.sum()]     # the first grid left doubt
    assert (angle < 3.0) == looks_again, angle


def test_a_plausible_first_pose_stays_where_the_second_looks_choice_is_refused(embedded_model, monkeypatch):
    """The second look only adds: where its choice among both grids' candidates would be refused,
    the first search's plausible pose stays, to the bit."""
    torch.set_num_threads(1)
    _, scan = _scan(embedded_model, 3)
    first = estimate_pose(embedded_model, scan, threads=1)
    monkeypatch.setattr(search, "DOUBTFUL_RMS", -1.0)     # every pose leaves doubt: the second look runs
    choose, choices = search.Search.choose, []

    def refusing_the_second(self, found):
        choices.append(len(found))
        if len(choices) > 1:
            raise StatfitError("the second look's choice, refused")
        return choose(self, found)

    monkeypatch.setattr(search.Search, "choose", refusing_the_second)
    again = estimate_pose(embedded_model, scan, threads=1)
    assert len(choices) == 2 and choices[1] > choices[0]
    assert np.array_equal(again.transform.rotation, first.transform.rotation)
    assert np.array_equal(again.transform.translation, first.transform.translation)
    assert np.array_equal(again.coefficients, first.coefficients)
