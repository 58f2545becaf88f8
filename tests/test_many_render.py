"""Many normal maps fitted in one program (issue 38, part 3): the renderer and the data term of B
views against each view's own, ``reconstruct_many`` against ``reconstruct``, and ``batch render
--together`` against one map at a time."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from conftest import run_cli
from statfit.objectives.normals import NormalMapObjective
from statfit.render.job import reconstruct
from statfit.render.many import reconstruct_many
from statfit.renderer.images import render_target
from statfit.renderer.silhouette import MeshAdjacency
from statfit.renderer.steady import SteadyRenderer
from statfit.structures.normal_map import NormalMap
from statfit.synth.sample import camera_for_view
from test_op_counts import WAITING, Counter

# (yaw, pitch, image size) of the views; the last is of another size (a group of its own).
VIEWS = ((20.0, 5.0, 72), (-30.0, 0.0, 72), (0.0, 12.0, 72), (10.0, 0.0, 60))


@pytest.fixture(scope="module")
def views(embedded_model):
    """Normal maps and cameras of a sample of the model per view, and other samples (fit starts)."""
    rng = np.random.default_rng(8)
    maps, cameras, starts = [], [], []
    for yaw, pitch, size in VIEWS:
        shape = embedded_model.sample(rng, 1.0)
        camera = camera_for_view(shape, yaw, pitch, size)
        maps.append(NormalMap(*render_target(shape, embedded_model.faces, camera)))
        cameras.append(camera)
        starts.append(embedded_model.sample(rng, 0.7))
    return maps, cameras, starts


def test_one_renderer_draws_each_view_as_its_own(embedded_model, views):
    """B meshes in B cameras, drawn into B images stacked: each image's covered pixels, triangles
    and silhouette blends are those of its own renderer (the triangles and pixels shifted)."""
    maps, cameras, starts = views
    faces = torch.as_tensor(embedded_model.faces, dtype=torch.long)
    adjacency = MeshAdjacency.from_faces(faces)
    vertices = torch.as_tensor(np.stack(starts[:3]))
    count, n = len(faces), embedded_model.num_vertices
    together = SteadyRenderer(faces, cameras[:3], adjacency, torch.float64, vertex_count=n)(vertices)
    for b in range(3):
        alone_renderer = SteadyRenderer(faces, cameras[b], adjacency, torch.float64)
        alone = alone_renderer(vertices[b])
        mine = (together.pixel >= b * alone_renderer.pixels) & (together.pixel < (b + 1) * alone_renderer.pixels)
        covered = alone.pixel < alone_renderer.pixels
        assert torch.equal(together.pixel[mine] - b * alone_renderer.pixels, alone.pixel[covered])
        assert torch.equal(together.face[mine] - b * count, alone.face[covered])
        torch.testing.assert_close(together.normals[:, mine], alone.normals[:, covered], rtol=1e-12, atol=1e-12)
        # The blends that weigh something (slots without a crossing weigh 0, wherever they point).
        hit = (together.target >= b * alone_renderer.pixels) & (together.target < (b + 1) * alone_renderer.pixels)
        hit &= together.weight > 0
        assert int(hit.sum()) == int((alone.weight > 0).sum()) > 0
        torch.testing.assert_close(together.weight[hit].sort().values, alone.weight[alone.weight > 0].sort().values,
                                   rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="one image size"):
        SteadyRenderer(faces, [cameras[0], cameras[3]], adjacency, torch.float64, vertex_count=n)


@pytest.mark.parametrize("sides", [{}, {"one_sided": True}, {"covering": True}, {"region": True}])
def test_one_term_for_many_views_is_the_sum_of_theirs(embedded_model, views, sides):
    """Value, per-view terms and gradient of the term over 3 views against the 3 views' own terms
    (float64): two-sided, one-sided and covering silhouettes, and a region."""
    maps, cameras, starts = views
    faces = torch.as_tensor(embedded_model.faces, dtype=torch.long)
    options = dict(sides)
    if options.pop("region", False):
        options["region_faces"] = torch.arange(len(faces)) % 3 != 0
    targets = [torch.as_tensor(np.where(m.mask[..., None], m.normals, 0.0)) for m in maps[:3]]
    masks = [torch.as_tensor(m.mask) for m in maps[:3]]
    batch = NormalMapObjective(torch.stack(targets), torch.stack(masks), cameras[:3], faces, **options)
    x = torch.as_tensor(np.stack(starts[:3])).requires_grad_(True)
    sum(batch(x).values()).backward()
    per_fit = batch.per_fit(x.detach())
    for b in range(3):
        alone = NormalMapObjective(targets[b], masks[b], cameras[b], faces, **options)
        xb = x.detach()[b].clone().requires_grad_(True)
        terms = alone(xb)
        sum(terms.values()).backward()
        for name, value in terms.items():
            assert per_fit[b][name] == pytest.approx(float(value.detach()), rel=1e-12, abs=1e-15)
        assert per_fit[b]["total"] == pytest.approx(float(sum(terms.values()).detach()), rel=1e-12)
        torch.testing.assert_close(x.grad[b], xb.grad, rtol=1e-10, atol=1e-13)


@pytest.mark.parametrize("method, align", [("statistical", "rigid"), ("hybrid", "none"), ("laplacian", "none")])
def test_maps_fitted_together_are_each_fitted_as_alone(embedded_model, views, method, align, monkeypatch):
    """``reconstruct_many`` (its own alignment per map, the stages of each image size together)
    ends where ``reconstruct`` ends for each map (float64); a map that cannot be fitted fails alone."""
    maps, cameras, _ = views
    if align != "none":   # the alignments are the slow part: two maps of one size, one of another, and
        maps, cameras = [maps[0], maps[1], maps[3]], [cameras[0], cameras[1], cameras[3]]
        monkeypatch.setattr("statfit.render.job.POSE_ITERATIONS", 40)   # 40 steps each, not 200 (53 s → 11)
    empty = NormalMap(maps[0].normals, np.zeros_like(maps[0].mask))
    options = dict(preset="paper", iterations=25, dtype=torch.float64, align=align)
    together = reconstruct_many(embedded_model, [*maps, empty], [*cameras, cameras[0]], method, **options)
    assert together[-1].fit is None and together[-1].error == "the normal map's mask has no foreground pixel"
    for normal_map, camera, fitted in zip(maps, cameras, together):
        assert fitted.error is None
        alone = reconstruct(embedded_model, normal_map, camera, method, **options)
        assert fitted.fit.iterations == alone.iterations == 25
        np.testing.assert_allclose(fitted.fit.vertices, alone.vertices, rtol=0, atol=1e-12)
        np.testing.assert_allclose(fitted.fit.transform.as_matrix(), alone.transform.as_matrix(), atol=1e-12)
        assert set(fitted.fit.loss) == {"normal", "silhouette", "total"}


def test_maps_of_a_face_mask_model_in_millimetres_are_fitted_together_as_alone(embedded_model):
    """Another model family's shape: the embedded head's face region alone, in mm (``auto`` gives it
    the one-sided silhouette); maps fitted together end where each fit alone ends (float64)."""
    from statfit.model.cut import region_part, rescaled

    mask_model = rescaled(region_part(embedded_model, "face"), 1000.0)
    rng = np.random.default_rng(2)
    maps, cameras = [], []
    for yaw in (-20.0, 0.0, 25.0):
        shape = mask_model.sample(rng, 1.0)
        cameras.append(camera_for_view(shape, yaw, 0.0, 64))
        maps.append(NormalMap(*render_target(shape, mask_model.faces, cameras[-1])))
    options = dict(preset="paper", iterations=20, dtype=torch.float64, align="none")
    together = reconstruct_many(mask_model, maps, cameras, "hybrid", **options)
    for normal_map, camera, fitted in zip(maps, cameras, together):
        alone = reconstruct(mask_model, normal_map, camera, "hybrid", **options)
        np.testing.assert_allclose(fitted.fit.vertices, alone.vertices, rtol=0, atol=1e-9)


def test_a_render_iteration_launches_one_fit_s_ops_for_many(embedded_model, views):
    """Ops per iteration of paper statistical for 1 and 6 maps together: about one fit's (+ 60),
    and no host wait."""
    maps, cameras, _ = views

    def per_iteration(fits: int) -> tuple[float, float]:
        counts = []
        for iterations in (10, 30):
            counter = Counter()
            with counter:
                reconstruct_many(embedded_model, [maps[0]] * fits, [cameras[0]] * fits, "statistical",
                                 preset="paper", align="none", iterations=iterations)
            counts.append((sum(counter.ops.values()),
                           sum(n for name, n in counter.ops.items() if any(w in name for w in WAITING))))
        return tuple((b - a) / 20 for a, b in zip(*counts))

    one, six = per_iteration(1), per_iteration(6)
    assert six[0] <= one[0] + 60, (one, six)
    assert six[1] == 0


def test_batch_render_together_fits_as_one_by_one(tmp_path):
    """``--together 3``: one worker fits 3 maps in one program (a corrupt one fails alone); each fit
    ends within float32 rounding of the one-by-one fit, and the settings say how it was made."""
    import json

    import trimesh

    maps = tmp_path / "maps"
    maps.mkdir()
    for seed in (1, 2, 3):
        assert run_cli(["synth", "normals", "--seed", str(seed), "--yaw", str(10 * seed), "--size", "64", "--out",
                        str(maps / f"m{seed}.exr")])[0] == 0
    (maps / "m4.exr").write_bytes(b"not an exr")
    outputs = {}
    for name, extra in (("together", ["--together", "4"]), ("alone", [])):
        out = tmp_path / name
        code, err = run_cli(["batch", "render", str(maps / "*.exr"), "--out-dir", str(out), "--workers", "1",
                             "--iterations", "40", "--align", "none", "-q", *extra])
        assert code == 1, err
        rows = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
        status = {row["output"]: row["status"] for row in rows if row.get("event") == "fit"}
        assert status == {"m1.ply": "done", "m2.ply": "done", "m3.ply": "done", "m4.ply": "failed"}
        outputs[name] = out
        if extra:
            assert next(row for row in rows if row.get("event") == "run")["settings"]["together"] == 4
    for seed in (1, 2, 3):
        together, alone = (trimesh.load(outputs[name] / f"m{seed}.ply", process=False).vertices
                           for name in ("together", "alone"))
        assert np.abs(together - alone).max() < 1e-3 * np.ptp(alone, axis=0).max()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_maps_fitted_together_on_cuda_are_captured_as_one_graph(embedded_model, views, monkeypatch):
    """On a GPU the stage of many maps is captured and replayed (one launch an iteration for all):
    it ends where the op-by-op fit ends. Not to the bit: CUDA's atomic adds sum in no fixed order, so
    two runs of one fit differ at float32 rounding, which 60 iterations of pixel decisions grow in
    places (an H100: 1.6e-4 m at most, 0.06% of the head); a replay of stale buffers would be off by
    the fit's own motion (~1e-2 m)."""
    maps, cameras, _ = views
    fits = {}
    for graphs in ("1", "0"):
        monkeypatch.setenv("STATFIT_CUDA_GRAPHS", graphs)
        fits[graphs] = reconstruct_many(embedded_model, maps[:3], cameras[:3], "statistical", preset="paper",
                                        align="none", iterations=60, device="cuda")
    for captured, eager in zip(fits["1"], fits["0"]):
        assert "graph" in captured.fit.stage_seconds and "graph" not in eager.fit.stage_seconds
        scale = np.ptp(eager.fit.vertices, axis=0).max()
        difference = np.abs(captured.fit.vertices - eager.fit.vertices)
        assert difference.max() < 2e-3 * scale and difference.mean() < 1e-4 * scale


def test_per_view_sums_through_partial_sums_are_the_sums():
    """The GPU's way (partial sums per view, against CUDA's serialised index_add) and the CPU's (one
    index_add, the default there) give each view's sums, against float64 sums by mask."""
    from statfit.objectives.normals import per_view_sums
    generator = torch.Generator().manual_seed(7)
    values = torch.randn(2, 50_000, generator=generator)
    owner = torch.randint(0, 5, (50_000,), generator=generator).sort().values        # 4 views and the dump
    expected = torch.stack([values.double()[:, owner == b].sum(dim=1) for b in range(5)], dim=1)
    assert torch.equal(per_view_sums(values, owner, 5), per_view_sums(values, owner, 5, spread=1))
    for spread in (1, 7, 1024):
        torch.testing.assert_close(per_view_sums(values, owner, 5, spread=spread).double(), expected,
                                   rtol=1e-5, atol=1e-3)
