"""What a normal map's bit depth costs a render fit: the rendering study's four ICT maps (512²,
expressions outside the model: docs/studies.md §5), four people of ICT's model (samples, seeds
1–4, σ 1, yaw 25°, pitch 5°, 512²) and four of the ICT face mask's (another family: the same
draws with the mask model) fitted by the render default from their float normals and from
the same normals rounded as an 8-bit and a 16-bit PNG stores them ((n + 1) / 2, rounded, decoded,
made unit again). Only the rounding differs: the maps go to ``reconstruct`` as arrays (that
statfit's PNG reader gives these values is tests/test_png16.py's and tests/test_normalmap_io.py's
claim). Error: mean vertex distance to the ground truth / its RMS radius
(``cases.relative_errors``), all, observed and unobserved vertices. One thread a fit, two fits at a
time (~10 min); rows in ``studies/results/png_bit_depth.json``.

    python studies/png_bit_depth.py [--report]
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "studies"))

from study_runs import study_main  # noqa: E402

RESULTS = ROOT / "studies" / "results" / "png_bit_depth.json"
CASES = ("jaw-open", "smile", "brow-up", "puff", "sample 1", "sample 2", "sample 3", "sample 4",
         "mask 1", "mask 2", "mask 3", "mask 4")
DEPTHS = ("float", "16-bit", "8-bit")


def rounded(normal_map, depth: str):
    """The map's normals as a PNG of ``depth`` stores and statfit decodes them."""
    import numpy as np

    from statfit.structures.normal_map import NormalMap

    if depth == "float":
        return normal_map
    top = {"16-bit": 65535.0, "8-bit": 255.0}[depth]
    code = np.round((normal_map.normals.astype(np.float64) + 1.0) / 2.0 * top)
    decoded = code / top * 2.0 - 1.0
    length = np.linalg.norm(decoded, axis=-1, keepdims=True)
    unit = np.where(normal_map.mask[..., None], decoded / np.maximum(length, 1e-12), 0.0)
    return NormalMap(unit.astype(np.float32), normal_map.mask, normal_map.camera)


def model_of(case: str):
    """The model a case is fitted with: ICT's head, or for 'mask' cases the ICT face mask
    (benchmarks/families.py: another family, millimetres, ~3,000 vertices)."""
    from cases import ict_model
    from families import family_model

    return family_model("ict-mask") if case.startswith("mask") else ict_model()


def in_span(case: str):
    """(ground truth, 512² NormalMap, camera, visible-vertex mask) of a person the case's model makes."""
    import numpy as np

    from statfit.geometry.metrics import visible_vertices
    from statfit.renderer.images import render_target
    from statfit.structures.normal_map import NormalMap
    from statfit.synth.sample import camera_for_view, sample_target

    model = model_of(case)
    truth = sample_target(model, np.random.default_rng(int(case.split()[1])))
    camera = camera_for_view(truth, 25.0, 5.0, 512)
    normals, mask = render_target(truth, model.faces, camera)
    return truth, NormalMap(normals, mask, camera), camera, visible_vertices(truth, model.faces, camera, mask)


def run_case(case: str, depth: str) -> dict:
    import time

    import torch

    torch.set_num_threads(1)
    import render_coarse_to_fine
    from cases import relative_errors

    from statfit.render.job import reconstruct

    truth, normal_map, camera, visible = (render_coarse_to_fine.make_case(case) if case in CASES[:4] else
                                          in_span(case))
    start = time.perf_counter()
    fit = reconstruct(model_of(case), rounded(normal_map, depth), camera, "default")
    return {"case": case, "depth": depth, "seconds": time.perf_counter() - start,
            **relative_errors(fit.vertices, truth, visible)}


GROUPS = {"expressions": CASES[:4], "in span": CASES[4:8], "mask, in span": CASES[8:]}


def report(rows: list[dict]) -> str:
    by = {(r["case"], r["depth"]): r for r in rows}

    def mean(depth: str, cases: tuple[str, ...], key: str = "all") -> float:
        values = [by[c, depth][key] for c in cases if (c, depth) in by]
        return sum(values) / len(values) if len(values) == len(cases) else float("nan")

    head = " | ".join(f"{g}: all | ÷ float | observed | unobserved" for g in GROUPS)
    lines = ["| normals | " + " | ".join(CASES) + f" | {head} |", "|---" * (len(CASES) + 1 + 4 * len(GROUPS)) + "|"]
    for depth in DEPTHS:
        cells = [f"{by[c, depth]['all'] * 100:.3f}" if (c, depth) in by else "–" for c in CASES]
        for cases in GROUPS.values():
            cells += [f"{mean(depth, cases) * 100:.3f}", f"{mean(depth, cases) / mean('float', cases):.3f}",
                      f"{mean(depth, cases, 'observed') * 100:.3f}", f"{mean(depth, cases, 'unobserved') * 100:.3f}"]
        lines.append(f"| {depth} | " + " | ".join(cells) + " |")
    return "Mean vertex error, % of the RMS radius\n\n" + "\n".join(lines)


if __name__ == "__main__":
    study_main(__doc__, run_case, lambda: [(c, d) for c in CASES for d in DEPTHS], RESULTS, report,
               key=lambda row: (row["case"], row["depth"]))
