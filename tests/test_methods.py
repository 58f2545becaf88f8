"""The method registry: validated settings, presets per job, a method added by one entry (in
Python or by another package's entry point, then usable as --method), and a hand-written loop."""
from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from statfit.errors import StatfitError
from statfit.core.methods import METHODS, Method, add_method, build, filtered_method, resolve
from statfit.registration.job import register
from statfit.core.settings import FitSpace, Settings
from statfit.synth.sample import sample_target, scan_from_view

BAD_SETTINGS = {
    "negative β": dict(beta=-1.0), "NaN β": dict(beta=math.nan), "negative λ": dict(lam=-1.0),
    "negative lr": dict(lr=-1.0), "zero lr": dict(lr=0.0), "infinite lr": dict(lr=math.inf),
    "NaN power": dict(power=math.nan), "zero power": dict(power=0.0), "negative mode gain": dict(mode_gain=-1.0),
    "zero iterations": dict(iterations=0), "huge iterations": dict(iterations=10**21),
    "fractional iterations": dict(iterations=2.5), "unknown Laplacian": dict(laplacian="fancy"),
    "unknown solver": dict(solver="magic"), "NaN noise": dict(noise=math.nan), "betas": dict(adam_betas=(1.0, 0.9)),
}


@pytest.mark.parametrize("case", sorted(BAD_SETTINGS))
def test_out_of_range_settings_are_refused_when_made(case):
    with pytest.raises(StatfitError):
        resolve("statistical", **BAD_SETTINGS[case])


def test_every_method_has_valid_settings_for_the_jobs_it_serves():
    for method in METHODS.values():
        assert method.tuned, method.name
        for job in method.tuned:
            assert resolve(method.name, job=job)[0].method == method.name
    with pytest.raises(StatfitError, match="regularized"):
        resolve("regularized", job="inpaint")


def test_lr_does_not_apply_to_the_gauss_newton_stage():
    with pytest.raises(StatfitError, match="Gauss"):
        resolve("pca", lr=0.1)
    assert resolve("pca", preset="paper", lr=0.1)[0].optimizer == "adam"


def test_pipeline_iterations_are_split_in_proportion():
    own = [s.iterations for s in resolve("default")]
    stages = resolve("default", iterations=100)
    assert sum(s.iterations for s in stages) == 100
    assert stages[0].iterations == round(100 * own[0] / sum(own))


def test_a_pipelines_step_size_is_its_gradient_stages():
    stages = resolve("default", lr=0.02)
    assert [s.optimizer for s in stages] == ["gauss-newton", "adam"]
    assert stages[0].lr == resolve("default")[0].lr and stages[1].lr == 0.02


def wiener_filter(settings: Settings, space: FitSpace, x0: torch.Tensor):
    """The docs' example (docs/method.md, "Adding a method"): the statistical filter with Wiener
    gains var_j / (var_j + var_1 / β) instead of (std_j / std_1)^γ."""
    from statfit.core.filters import StatisticalFilter

    variance = space.std**2
    return StatisticalFilter(space.basis_t, settings.beta, mode_gain=variance / (variance + variance[0] / settings.beta))


def test_a_method_added_by_one_entry_fits(embedded_model, rng):
    add_method(Method("wiener", filtered_method(wiener_filter),
                      tuned={"register": Settings("wiener", 300, 0.05, beta=1000.0)}))
    try:
        target = sample_target(embedded_model, rng)
        points = scan_from_view(target, embedded_model.faces, rng, 2000, 20.0)
        fit = register(embedded_model, points, "wiener")
        error = lambda v: np.linalg.norm(v - target, axis=1).mean()  # noqa: E731
        assert error(fit.vertices) < 0.5 * error(embedded_model.template)
    finally:
        METHODS.pop("wiener")


def test_a_hand_written_loop_drives_any_parametrisation(embedded_model):
    """The README's ten-line loop: any torch loss, plain autograd, the registry's optimiser."""
    space = FitSpace.of(embedded_model)
    target = space.mean + (space.basis_t[0] * space.std[0] * 1.5).view_as(space.mean)   # one mode, 1.5 std
    for method in ("statistical", "pca", "regularized"):
        (settings,) = resolve(method, preset="paper", iterations=1)
        param, optimizer = build(settings, space, space.mean)
        for _ in range(300):
            loss = (param.vertices() - target).square().sum()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        assert float((param.vertices().detach() - target).norm()) < 0.2 * float((space.mean - target).norm()), method


PLUGIN = """
from statfit.core.methods import Method, add_method, filtered_method
from statfit.core.settings import Settings
from statfit.core.filters import StatisticalFilter

def half_gain(settings, space, x0):
    return StatisticalFilter(space.basis_t, settings.beta, mode_gain=0.5 * (space.std / space.std[0]))

add_method(Method("half-gain", filtered_method(half_gain), tuned={"register": Settings("half-gain", 50, 0.05)}))
"""


def test_a_plugin_package_adds_a_cli_method(tmp_path, embedded_model, rng):
    (tmp_path / "statfit_half_gain.py").write_text(PLUGIN)
    info = tmp_path / "statfit_half_gain-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: statfit-half-gain\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[statfit.methods]\nhalf-gain = statfit_half_gain\n")
    points = scan_from_view(sample_target(embedded_model, rng), embedded_model.faces, rng, 1000, 0.0)
    from statfit.io.mesh import points_bytes
    (tmp_path / "scan.ply").write_bytes(points_bytes(points))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    run = subprocess.run([sys.executable, "-c", "from statfit_cli.main import main; main()", "register",
                          str(tmp_path / "scan.ply"), "--method", "half-gain", "--out", str(tmp_path / "fit.ply"),
                          "-q", "--json"], capture_output=True, text=True, env=env)
    assert run.returncode == 0, run.stderr
    assert '"method": "half-gain"' in run.stdout and (tmp_path / "fit.ply").is_file()


BAD_OPTIONS = [["--beta", "-1"], ["--beta", "-0.5"], ["--lr", "-1"], ["--lr", "nan"], ["--lam", "-1"],
               ["--power", "0"], ["--iterations", "999999999999999999999"], ["--iterations", "0"]]


@pytest.mark.parametrize("command", ["register", "render", "inpaint"])
@pytest.mark.parametrize("option", BAD_OPTIONS, ids=" ".join)
def test_every_command_refuses_bad_settings_the_same_way(command, option, tmp_path, capsys):
    """One line naming the setting, exit 2, nothing written, before any input is read (the inputs
    here are files no reader would take)."""
    from statfit_cli.main import main

    inputs = tmp_path / "inputs"
    inputs.mkdir()
    for name in ("junk.ply", "junk.exr", "junk.png", "m.png"):
        (inputs / name).write_bytes(b"not what its name says")
    argv = {"register": ["register", str(inputs / "junk.ply"), "--method", "statistical"],
            "render": ["render", str(inputs / "junk.exr"), "--method", "hybrid"],
            "inpaint": ["inpaint", str(inputs / "junk.png"), "--mask", str(inputs / "m.png"),
                        "--method", "laplacian"]}[command]
    if command == "inpaint" and option[0] == "--power":
        option = ["--lam", "nan"]  # inpaint has no --power
    with pytest.raises(SystemExit) as exit_info:
        main([*argv, *option, "--out", str(tmp_path / "out.ply" if command != "inpaint" else tmp_path / "o.png")])
    err = capsys.readouterr().err
    setting = option[0].lstrip("-").replace("lr", "lr (the step size)")
    assert exit_info.value.code == 2 and err.count("\n") == 1 and err.startswith(f"statfit: error: {setting}"), err
    assert [path.name for path in tmp_path.iterdir()] == ["inputs"]


def test_gauss_newton_is_for_the_coefficients_only():
    with pytest.raises(StatfitError, match="Gauss"):
        Settings("statistical", 10, 0.0, optimizer="gauss-newton")


@pytest.mark.parametrize("lr", [-1.0, 0.0, float("nan"), float("inf")])
def test_a_pipelines_bad_step_size_is_refused_naming_it(lr):
    with pytest.raises(StatfitError, match="lr"):
        resolve("default", lr=lr)


@pytest.mark.parametrize("settings", [dict(method="statistical", lr=0.01, prior=0.1),
                                      dict(method="pca", lr=0.0, optimizer="gauss-newton", prior=0.1),
                                      dict(method="pca", lr=0.01, prior=-1.0),
                                      dict(method="pca", lr=0.01, prior=math.nan)])
def test_a_coefficient_prior_is_for_pcas_adam_stage_only(settings):
    with pytest.raises(StatfitError, match="prior"):
        Settings(iterations=10, **settings)


def test_pcas_coefficient_prior_pulls_each_coefficient_to_zero(embedded_model):
    """w · mean(c²): value and gradient 2 w c / K in closed form, beside the data term's."""
    from statfit.core.parametrize import PCACoefficients

    space = FitSpace.of(embedded_model)
    k = len(space.std)
    start = torch.linspace(-2.0, 2.0, k, dtype=space.mean.dtype)
    param = PCACoefficients(space.mean, space.basis_t * space.std[:, None], start, prior=0.5)
    x = param.vertices()
    terms = param.prior(x)
    torch.testing.assert_close(terms["prior"], 0.5 * (start**2).mean())
    terms["prior"].backward()
    torch.testing.assert_close(param.coeffs.grad, 2 * 0.5 * start / k)
    assert PCACoefficients(space.mean, space.basis_t, start).prior(x) == {}   # no weight, no term
