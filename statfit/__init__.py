"""statfit: fit a template mesh to limited observations with statistical gradient filtering."""
from importlib import metadata

__version__ = metadata.version("statfit")

from statfit.errors import DivergenceError, StatfitError
from statfit.model import StatModel, load_model, model_from_arrays, save_model
from statfit.importers import import_model
from statfit.build import build_model, build_model_from_files
from statfit.inverse_render import reconstruct
from statfit.register import register
from statfit.stages import Fit

__all__ = ["StatModel", "load_model", "model_from_arrays", "save_model", "import_model", "build_model",
           "build_model_from_files", "register", "reconstruct", "Fit",
           "StatfitError", "DivergenceError", "__version__"]
