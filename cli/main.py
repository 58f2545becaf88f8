"""The ``statfit`` command: sub-commands and the one place where errors become exit code 2."""
from __future__ import annotations

import importlib.abc
import importlib.util
import os
import sys
import warnings

import typer
import typer.main

from statfit import __version__
from statfit.errors import StatfitError
from statfit_cli import batch, demo, evaluate, inpaint, model, register, render, splat, synth, texture

app = typer.Typer(
    help="Fit a template mesh to limited observations (a partial scan, a normal map, or photographs) with statistical gradient filtering.\n\n"
         "Start with `statfit demo`; `statfit COMMAND --help` explains each command.",
    no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False, rich_markup_mode=None,
)
def _version(show: bool) -> None:
    if show:
        print(f"statfit {__version__}")
        raise typer.Exit()


@app.callback()
def _options(version: bool = typer.Option(False, "--version", help="Print the version and exit.",
                                          callback=_version, is_eager=True)) -> None:
    """Options of statfit itself (before the command)."""


app.command("register")(register.register)
app.command("render")(render.render)
app.command("demo")(demo.demo)
app.command("eval")(evaluate.evaluate)
app.command("inpaint")(inpaint.inpaint)
app.command("splat")(splat.splat)
app.command("splat-render")(splat.splat_render)
app.add_typer(synth.app, name="synth")
app.add_typer(batch.app, name="batch")
model.app.command("build-texture")(texture.build_texture)
app.add_typer(model.app, name="model")


def _set_up_before_each_command(command) -> None:
    """Make every command of the click tree ``command`` set up the process for fitting once its options
    are parsed and before its work: subnormals flushed to zero before any parallel kernel, so every
    worker thread inherits it. ``--help``, a refused option and a refused path never import torch
    (the commands import the library once their paths are checked)."""
    for child in getattr(command, "commands", {}).values():
        _set_up_before_each_command(child)
    work = command.callback
    if work is None or hasattr(command, "commands"):      # a group's own callback: not a command's work
        return

    def set_up_then_work(*args, **kwargs):
        _flush_denormals_once_torch_loads()
        return work(*args, **kwargs)

    command.callback = set_up_then_work


class _FlushWhenTorchLoads(importlib.abc.MetaPathFinder):
    """A one-shot import hook: the first ``import torch`` runs torch's own loader, then flushes
    subnormals on this thread, before anything can run a parallel kernel."""

    def find_spec(self, name, path=None, target=None):
        if name != "torch":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        if spec is not None and spec.loader is not None:
            load = spec.loader.exec_module

            def load_then_flush(module):
                load(module)
                module.set_flush_denormal(True)

            spec.loader.exec_module = load_then_flush
        return spec


def _flush_denormals_once_torch_loads() -> None:
    """Flush subnormals now if torch is loaded (an earlier command in this process), else right
    after the command imports it: a command that refuses its input does not pay torch's import."""
    if "torch" in sys.modules:
        from statfit.core.threads import flush_denormals_everywhere

        flush_denormals_everywhere()
    elif not any(isinstance(finder, _FlushWhenTorchLoads) for finder in sys.meta_path):
        sys.meta_path.insert(0, _FlushWhenTorchLoads())


def _fail(message: str) -> None:
    print(f"statfit: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def main(argv: list[str] | None = None) -> None:
    """Run the CLI on ``argv`` (default: the process's arguments); user errors, and any fault inside
    a fit, print one line on stderr and exit with code 2."""
    command = typer.main.get_command(app)
    _set_up_before_each_command(command)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # library warnings are printed by the commands themselves
        try:
            code = command(args=argv, standalone_mode=False, prog_name="statfit")
        except StatfitError as exc:
            _fail(str(exc))
        except typer.Abort:
            _fail("aborted")
        except typer.TyperException as exc:  # typer's (vendored click) usage errors
            if type(exc).__name__ == "NoArgsIsHelpError":  # bare `statfit` or `statfit model`: show help
                print(exc.format_message())
                raise SystemExit(0)
            _fail(exc.format_message().replace("\n", " "))
        except KeyboardInterrupt:
            _fail("interrupted")
        except BrokenPipeError:
            raise SystemExit(1)
        except MemoryError:
            _fail("out of memory (try a smaller input, fewer modes with --k, or --device cpu)")
        except Exception as exc:  # a fault inside a fit: one line, never a traceback (STATFIT_DEBUG=1 shows it)
            if os.environ.get("STATFIT_DEBUG"):
                raise
            first = (str(exc).splitlines() or [""])[0]
            _fail(f"the fit failed inside statfit ({type(exc).__name__}: {first}); nothing was written. Please "
                  "report it with the inputs; STATFIT_DEBUG=1 shows where")
    raise SystemExit(code if isinstance(code, int) else 0)


if __name__ == "__main__":
    main()
