"""CUDA graphs of the fitting loop (:mod:`statfit.core.graphs`) and the parts they need.

On a CPU: which fits the rule captures, the capturable optimiser step against the plain one, the
dense Laplacian solve against the sparse factorisation, the renderer's overflow check when the loop
counts the calls. On a GPU (skipped without one; the CUDA suite runs them): a captured fit against
the same fit run op by op, and a fit whose view outgrows the renderer's buffers being captured
again."""
from __future__ import annotations

import contextlib

import numpy as np
import pytest
import torch

from statfit import reconstruct
from statfit.core import graphs
from statfit.core.filters import HybridFilter, LaplacianFilter, StatisticalFilter
from statfit.core.fit import StageTimer
from statfit.core.optim import UniformAdam, make_capturable
from statfit.core.parametrize import FilteredVertices
from statfit.core.solvers import DENSE_LIMIT, auto_solver, make_solver
from statfit.errors import StatfitError
from statfit.objectives.normals import NormalMapObjective
from statfit.renderer import steady_buffers

from conftest import normal_map_scene

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


@pytest.fixture(scope="module")
def grid():
    """A 12 × 12 grid mesh: vertices (144, 3), faces (242, 3)."""
    ii, jj = np.meshgrid(np.arange(12), np.arange(12), indexing="ij")
    vertices = np.stack([ii.ravel(), jj.ravel(), np.zeros(144)], axis=1).astype(float)
    index = np.arange(144).reshape(12, 12)
    a, b, c, d = index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, 1:].ravel()
    return vertices, np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)])


def test_the_rule_captures_static_fits_on_cuda_only(grid, monkeypatch):
    """Statistical and dense-solved hybrid fits of a capturable objective on CUDA; never on the CPU,
    never through cholespy (its kernels run on CUDA's legacy stream), nor with STATFIT_CUDA_GRAPHS=0."""
    vertices, faces = grid
    basis_t = torch.linalg.qr(torch.randn(432, 5, dtype=torch.float64))[0].T.float()
    objective = type("Static", (), {"capturable": True, "deferred_checks": True})()
    cuda_device, cpu = torch.device("cuda"), torch.device("cpu")

    def param(filter_):
        p = FilteredVertices(torch.zeros(144, 3), filter_)
        return p, [UniformAdam(p.parameters())]

    statistical = param(StatisticalFilter(basis_t, 30.0))
    sparse = param(HybridFilter(basis_t, 1.0, LaplacianFilter(vertices, faces, 19.0)))
    dense = param(HybridFilter(basis_t, 1.0, LaplacianFilter(vertices, faces, 19.0, solver="dense")))
    assert graphs.capturable(objective, statistical[1], cuda_device, statistical[0])
    assert graphs.capturable(objective, dense[1], cuda_device, dense[0])
    assert not graphs.capturable(objective, sparse[1], cuda_device, sparse[0])
    assert not graphs.capturable(objective, statistical[1], cpu, statistical[0])
    eager_objective = type("Eager", (), {"capturable": False, "deferred_checks": True})()
    assert not graphs.capturable(eager_objective, statistical[1], cuda_device, statistical[0])
    monkeypatch.setenv("STATFIT_CUDA_GRAPHS", "0")
    assert not graphs.capturable(objective, statistical[1], cuda_device, statistical[0])


def test_the_capturable_step_is_the_plain_step():
    """UniformAdam with its step count on the device takes the same steps (float64: to rounding),
    switched over mid-fit as the loop does before a capture."""
    torch.manual_seed(0)
    a = torch.randn(60, 3, dtype=torch.float64, requires_grad=True)
    b = a.detach().clone().requires_grad_(True)
    plain, switched = UniformAdam([a], lr=0.02), UniformAdam([b], lr=0.02)
    for step in range(40):
        gradient = torch.randn(60, 3, dtype=torch.float64)
        a.grad, b.grad = gradient.clone(), gradient.clone()
        plain.step()
        switched.step()
        if step == 4:
            assert make_capturable(switched)
    torch.testing.assert_close(b, a, rtol=0, atol=1e-13)
    assert float(switched.state[b]["step"]) == 40
    assert not make_capturable(torch.optim.SGD([b], lr=0.1))


def test_the_dense_solve_solves_the_system(grid, monkeypatch):
    """The dense inverse's product solves (I + λL) x = b (residual), as the sparse factorisation
    does; meshes beyond its limit are refused in one line."""
    vertices, faces = grid
    filter_ = LaplacianFilter(vertices, faces, 19.0, solver="dense", dtype=torch.float64)
    rhs = torch.randn(144, 3, dtype=torch.float64)
    solved = filter_(rhs)
    sparse = LaplacianFilter(vertices, faces, 19.0, dtype=torch.float64)(rhs)
    torch.testing.assert_close(solved, sparse, rtol=1e-9, atol=1e-9)
    from statfit.core.laplacian import smoothing_matrix
    system = smoothing_matrix(vertices, faces, 19.0, "uniform")
    np.testing.assert_allclose(system @ solved.numpy(), rhs.numpy(), atol=1e-9)
    assert auto_solver(144, torch.device("cuda")) == "dense"
    assert auto_solver(144, torch.device("cpu")) == auto_solver(DENSE_LIMIT + 1, torch.device("cuda")) == "cholespy"
    monkeypatch.setattr("statfit.core.solvers.DENSE_LIMIT", 100)
    with pytest.raises(StatfitError, match="at most 100 vertices"):
        make_solver(system, "dense")
    assert DENSE_LIMIT >= 11_248  # ICT's head


def test_the_loop_counts_the_replays_for_the_renderer(embedded_model, monkeypatch):
    """With the renderer's calls counted by ``replayed`` (as the loop does after each replay), the
    overflow check still reads every CHECK_EVERY counts and forgets a buffer that was too small; a
    call while no buffer overflowed forgets nothing."""
    normal_map, camera = normal_map_scene(embedded_model, 64)
    from statfit.render.job import camera_space_normals
    target = torch.as_tensor(camera_space_normals(normal_map, camera), dtype=torch.float32)
    faces = torch.as_tensor(embedded_model.faces, dtype=torch.long)
    objective = NormalMapObjective(target, torch.as_tensor(normal_map.mask), camera, faces)
    x = torch.as_tensor(embedded_model.template, dtype=torch.float32)
    objective(x)
    renderer = objective._renderer
    calls = renderer._calls
    assert not any(objective.replayed() for _ in range(steady_buffers.CHECK_EVERY))
    assert renderer._calls == calls + steady_buffers.CHECK_EVERY
    renderer._sizes["pixels"] = 1               # as if the view had grown past its buffer
    objective(x)
    due = -(renderer._calls + 1) % steady_buffers.CHECK_EVERY      # the replay whose count is a multiple of CHECK_EVERY
    flags = [objective.replayed() for _ in range(steady_buffers.CHECK_EVERY)]
    assert flags == [i == due for i in range(steady_buffers.CHECK_EVERY)]
    assert "pixels" not in renderer._sizes


class _NoStream:
    def wait_stream(self, other) -> None:
        pass


def _graphs_reaching(parameters: list[torch.Tensor]) -> list[str]:
    """The live tensors whose autograd graph reaches one of ``parameters``: their grad_fn's name."""
    import gc

    wanted = {id(each) for each in parameters}
    found = []
    # type(), not isinstance(): the latter reads __class__, which warns on torch's deprecated aliases.
    for tensor in (obj for obj in gc.get_objects() if issubclass(type(obj), torch.Tensor) and obj.grad_fn is not None):
        nodes, seen = [tensor.grad_fn], set()
        while nodes:
            node = nodes.pop()
            if node is None or id(node) in seen:
                continue
            seen.add(id(node))
            if id(getattr(node, "variable", None)) in wanted:
                found.append(type(tensor.grad_fn).__name__)
                break
            nodes.extend(child for child, _ in node.next_functions)
    return found


def test_no_autograd_graph_reaching_the_parameters_is_alive_at_a_capture(embedded_model, monkeypatch):
    """At every capture (the alignment's pose search and each stage of the fit, paper and default,
    one map and two together), no tensor still holds an earlier iteration's autograd graph. One that
    did ties the parameters' gradient accumulation to the warm-up's stream: torch 2.11 warned of it
    on the session-33 H200 ("The AccumulateGrad node's stream does not match ...") and a graph kept
    so may wait for that stream. It was the renderer's last visibility, which kept the vertices'
    screen positions with their graph. Simulated on a CPU: the loop runs its warm-up and, where it
    would capture, the live tensors are searched."""
    from statfit.core import fit, pose
    from statfit.render.many import reconstruct_many

    monkeypatch.setattr(torch.cuda, "Stream", lambda *args, **kwargs: _NoStream())
    monkeypatch.setattr(torch.cuda, "current_stream", lambda *args, **kwargs: _NoStream())
    monkeypatch.setattr(torch.cuda, "stream", lambda stream: contextlib.nullcontext())
    for module in (fit, pose):
        monkeypatch.setattr(module, "capturable", lambda *args, **kwargs: True)
    seen: list[list[str]] = []

    def capture(self) -> None:
        seen.append(_graphs_reaching([p for each in self._optimizers for group in each.param_groups for p in group["params"]]))
        self.failure = "simulated on a CPU"
    monkeypatch.setattr(graphs.CapturedIteration, "_capture", capture)
    normal_map, camera = normal_map_scene(embedded_model, 64)
    reconstruct(embedded_model, normal_map, camera, "statistical", preset="paper", iterations=20)
    # Without the alignment: a capture refused here leaves its ~300 pose steps op by op (5 s each).
    reconstruct(embedded_model, normal_map, camera, "default", iterations=20, align="none")
    reconstruct_many(embedded_model, [normal_map, normal_map], [camera, camera], "statistical", preset="paper",
                     iterations=20, align="none")
    assert len(seen) >= 6 and seen == [[]] * len(seen), seen


@cuda
def test_a_captured_fit_is_the_fit_run_op_by_op(embedded_model, monkeypatch):
    """A paper-statistical render on CUDA, captured (one capture, then replays), against the same
    fit with capturing off: the same vertices to float32 rounding over 60 iterations."""
    normal_map, camera = normal_map_scene(embedded_model, 64)

    def fit(graphs_on: str):
        monkeypatch.setenv("STATFIT_CUDA_GRAPHS", graphs_on)
        timer = StageTimer()
        result = reconstruct(embedded_model, normal_map, camera, "statistical", preset="paper", align="none",
                             iterations=60, device="cuda", timer=timer)
        return result, timer

    captured, timer = fit("1")
    eager, eager_timer = fit("0")
    assert timer.notes["graph"] == "captured 1×", timer.notes
    assert "graph" not in eager_timer.notes
    scale = np.ptp(eager.vertices, axis=0).max()
    np.testing.assert_allclose(captured.vertices, eager.vertices, atol=1e-4 * scale)
    assert captured.loss["normal"] == pytest.approx(eager.loss["normal"], rel=1e-3)


@cuda
def test_a_hybrid_fit_with_the_dense_solve_is_captured(embedded_model, monkeypatch):
    """The hybrid filter with the dense Laplacian solve is captured and fits as the cholespy one does."""
    normal_map, camera = normal_map_scene(embedded_model, 64)
    timer = StageTimer()
    dense = reconstruct(embedded_model, normal_map, camera, "hybrid", align="none", iterations=60, device="cuda",
                        timer=timer, solver="dense")
    sparse = reconstruct(embedded_model, normal_map, camera, "hybrid", align="none", iterations=60, device="cuda")
    assert timer.notes["graph"] == "captured 1×", timer.notes
    scale = np.ptp(sparse.vertices, axis=0).max()
    np.testing.assert_allclose(dense.vertices, sparse.vertices, atol=1e-3 * scale)


@cuda
def test_a_view_that_outgrows_its_buffers_is_captured_again(embedded_model, monkeypatch):
    """Buffers sized without margin overflow as the fit moves: the loop runs eagerly and captures
    again, and the fit ends where the fit run op by op does."""
    monkeypatch.setattr(steady_buffers, "MARGIN", 1.0)
    monkeypatch.setattr(steady_buffers, "FLOOR", 0)
    normal_map, camera = normal_map_scene(embedded_model, 64)
    start = embedded_model.template * 0.9 + embedded_model.template.mean(axis=0) * 0.1   # grows towards the map

    def fit(graphs_on: str):
        monkeypatch.setenv("STATFIT_CUDA_GRAPHS", graphs_on)
        timer = StageTimer()
        result = reconstruct(embedded_model, normal_map, camera, "statistical", preset="paper", align="none",
                             init=start, iterations=200, device="cuda", timer=timer)
        return result, timer

    captured, timer = fit("1")
    eager, _ = fit("0")
    assert timer.notes["graph"].startswith("captured") and timer.notes["graph"] != "captured 1×", timer.notes
    scale = np.ptp(eager.vertices, axis=0).max()
    np.testing.assert_allclose(captured.vertices, eager.vertices, atol=1e-3 * scale)
