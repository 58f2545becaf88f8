"""The fitting loop's render objective of this tree against a git revision's, side by side in one process.

    python benchmarks/render_ab.py [--against REV] [--size 512] [--rounds 20] [--model ict|embedded] [--every K]

Issue 38's CPU target is a ratio (a render iteration at 512² on one core ≤ 0.7× a baseline's), and
separate runs on one machine vary by ±15% (docs/benchmarks.md §12). So both objectives are timed in one
process on one thread, alternating every 10 calls at the same vertices. The revision's renderer
(``statfit/renderer/steady.py``, ``steady_parts.py``, ``steady_buffers.py``) and objective
(``statfit/objectives/normals.py``) are read with ``git show`` and imported under other names;
everything else is this tree's. The case: ICT jaw-open (``benchmarks/cases.py``), or a sample of the
embedded head (``--model embedded``), seen at yaw 20°. Prints each objective's min and median ms per
call with its backward, the ratio of the medians, and whether the values and gradients are the same bits
(``torch.equal``). ``--every K``: this tree's objective refreshes its visibility every K calls (the
render default's reuse, docs/method.md; the calls between reuse it at the same vertices, which gives the
same bits: what the loop pays).
"""
from __future__ import annotations

import argparse
import importlib
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

# The revision's modules, each importing the others under their new names (the buffers' module
# is not in revisions before session 23's).
MODULES = {"statfit.renderer.steady_buffers": "statfit/renderer/steady_buffers.py",
           "statfit.renderer.steady_parts": "statfit/renderer/steady_parts.py",
           "statfit.renderer.steady": "statfit/renderer/steady.py",
           "statfit.objectives.normals": "statfit/objectives/normals.py"}
OPTIONAL = {"statfit.renderer.steady_buffers"}
ALTERNATE_EVERY = 10


def revision_objective(revision: str, folder: Path) -> type:
    """The ``NormalMapObjective`` class of ``revision``, with that revision's renderer."""
    renamed = {name: "_rev_" + name.rsplit(".", 1)[1] for name in MODULES}
    for name, path in MODULES.items():
        done = subprocess.run(["git", "-C", str(ROOT), "show", f"{revision}:{path}"], capture_output=True, text=True)
        if done.returncode != 0 and name in OPTIONAL:
            continue
        if done.returncode != 0:
            sys.exit(f"render_ab: cannot read {path} at {revision}: {done.stderr.strip()}")
        source = done.stdout
        for other, new_name in renamed.items():
            source = source.replace(f"from {other} import", f"from {new_name} import")
        (folder / f"{renamed[name]}.py").write_text(source)
    for new_name in renamed.values():     # another revision's, read earlier in this process
        sys.modules.pop(new_name, None)
    sys.path.insert(0, str(folder))
    try:
        return importlib.import_module(renamed["statfit.objectives.normals"]).NormalMapObjective
    finally:
        sys.path.remove(str(folder))      # the folder goes; the modules stay imported


def case(model_name: str, size: int):
    """The model, the target's normal map and its camera."""
    from statfit.model.statmodel import default_model_path, load_model
    from statfit.renderer.images import render_target
    from statfit.structures.normal_map import NormalMap
    from statfit.synth.sample import camera_for_view

    if model_name == "ict":
        from cases import ict_model, normal_case

        named = normal_case("jaw-open", size)
        return ict_model(), named.normal_map, named.camera
    model = load_model(default_model_path())
    shape = model.sample(np.random.default_rng(3), 1.0)
    camera = camera_for_view(shape, 20.0, 5.0, size)
    return model, NormalMap(*render_target(shape, model.faces, camera)), camera


def compare(revision: str, model_name: str, size: int, rounds: int, every: int = 1) -> dict:
    """Both objectives' ms per call (lists), whether their values and gradients are the same bits, and
    the modules the revision's objective and renderer came from."""
    from statfit.objectives.normals import NormalMapObjective
    from statfit.render.job import PosedView

    torch.set_num_threads(1)
    model, normal_map, camera = case(model_name, size)
    view = PosedView.of(model, normal_map, camera, torch.device("cpu"), torch.float32, align="none")
    # The shared options, less the visibility's reuse (this tree's alone, set below; refreshed every call).
    options = {name: value for name, value in view.options.items() if not name.startswith("visibility_")}
    with tempfile.TemporaryDirectory() as folder:
        old = revision_objective(revision, Path(folder))(view.target, view.mask, view.camera, **options)
    new = NormalMapObjective(view.target, view.mask, view.camera, **options, visibility_every=every)
    x = view.start.clone().requires_grad_(True)

    def call(objective) -> tuple[dict, torch.Tensor]:
        x.grad = None
        terms = objective(x)
        sum(terms.values()).backward()
        return {name: value.detach() for name, value in terms.items()}, x.grad.clone()

    def block(objective) -> float:
        start = time.perf_counter()
        for _ in range(ALTERNATE_EVERY):
            call(objective)
        return (time.perf_counter() - start) / ALTERNATE_EVERY * 1e3

    (old_terms, old_grad), (new_terms, new_grad) = call(old), call(new)
    same = old_terms.keys() == new_terms.keys() and all(torch.equal(old_terms[k], new_terms[k]) for k in old_terms) \
        and torch.equal(old_grad, new_grad)
    for objective in (old, new, old, new):    # warm both, the buffers sized
        block(objective)
    times = {"revision": [], "tree": []}
    for _ in range(rounds):
        times["revision"].append(block(old))
        times["tree"].append(block(new))
    return {"times": times, "same_bits": same,
            "revision_modules": (type(old).__module__, type(old._renderer).__module__)}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--against", default="HEAD", help="the git revision to compare with (default HEAD)")
    parser.add_argument("--size", type=int, default=512, help="image size in pixels (default 512)")
    parser.add_argument("--rounds", type=int, default=20, help="alternations of 10 calls each (default 20)")
    parser.add_argument("--model", choices=("ict", "embedded"), default="ict")
    parser.add_argument("--every", type=int, default=1, help="this tree's calls per visibility refresh (default 1)")
    args = parser.parse_args(argv)
    if args.every < 1 or args.size < 16 or args.rounds < 1:
        parser.error("--every and --rounds must be 1 or more, --size 16 or more")
    result = compare(args.against, args.model, args.size, args.rounds, args.every)
    medians = {}
    for name, values in result["times"].items():
        medians[name] = statistics.median(values)
        print(f"{name:8s} ({args.against if name == 'revision' else 'this tree'}): "
              f"min {min(values):.2f} median {medians[name]:.2f} ms a call, {args.model} {args.size}²")
    print(f"this tree ÷ {args.against}: {medians['tree'] / medians['revision']:.3f} (medians); "
          f"same values and gradients to the bit: {result['same_bits']}")
    return result


if __name__ == "__main__":
    main()
