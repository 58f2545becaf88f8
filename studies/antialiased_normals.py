"""The normal term with and without antialiased normals, side by side, on the face cases of the
rendering studies (docs/studies.md §5, §11: four ICT normal maps at 512²; the body study, §13,
measures the bodies).

``plain`` is the normal term as it was until 2026-11-25 (commit 906bc56): rasterised normals, which
have no gradient where one surface hides another inside the mask; ``antialiased`` is the shipped
:class:`statfit.objectives.normals.NormalMapObjective`. Both with the silhouette term, the default
render pipeline, one thread. Error: mean vertex distance to the ground truth / its RMS radius
(``cases.relative_errors``). Results: ``studies/results/antialiased_normals.json`` (~6 min alone).

    python studies/antialiased_normals.py [--method default]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "studies"))

RESULTS = ROOT / "studies" / "results" / "antialiased_normals.json"


def plain_normal_term(self, vertices):
    """NormalMapObjective.__call__ as of commit 906bc56: the normals rasterised, not antialiased."""
    from statfit.renderer import fragment_normals, rasterize, silhouette_crossings

    fragments = rasterize(vertices, self.faces, self.camera)
    normals = fragment_normals(vertices, self.faces, fragments, self.camera)
    target = self._normals_by_pixel.index_select(1, fragments.pixel)
    both = self._mask_by_pixel.index_select(0, fragments.pixel)
    terms = {"normal": ((normals - target).abs().sum(dim=0) * both).sum() / both.sum().clamp_min(1.0)}
    if self.silhouette_weight:
        mask = silhouette_crossings(fragments, self.faces, self.adjacency).blend(fragments.coverage(vertices.dtype))
        terms["silhouette"] = self.silhouette_weight * (mask[..., 0] - self.mask).square().sum() / self.count
    return terms


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--method", default="default")
    args = parser.parse_args()
    import torch

    torch.set_num_threads(1)
    import render_coarse_to_fine
    from cases import ict_model, relative_errors

    from statfit.render.job import reconstruct
    from statfit.objectives.normals import NormalMapObjective

    shipped = NormalMapObjective.__call__
    rows = []
    for case in render_coarse_to_fine.CASE_NAMES:
        truth, normal_map, camera, visible = render_coarse_to_fine.make_case(case)
        for objective, call in (("plain", plain_normal_term), ("antialiased", shipped)):
            NormalMapObjective.__call__ = call
            started = time.perf_counter()
            fit = reconstruct(ict_model(), normal_map, camera, args.method, threads=1)
            row = {"case": case, "method": args.method, "objective": objective,
                   **relative_errors(fit.vertices, truth, visible), "seconds": time.perf_counter() - started}
            print(json.dumps(row), flush=True)
            rows.append(row)
    NormalMapObjective.__call__ = shipped
    RESULTS.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
