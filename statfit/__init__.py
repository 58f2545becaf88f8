"""statfit: fit a template mesh to limited observations with statistical gradient filtering."""
from importlib import metadata

__version__ = metadata.version("statfit")

from statfit.errors import DivergenceError, StatfitError
from statfit.model.statmodel import StatModel, load_model, model_from_arrays, save_model
from statfit.model.importers import import_model
from statfit.model.build import build_model, build_model_from_files
from statfit.render.job import reconstruct
from statfit.render.many import reconstruct_many
from statfit.registration.job import register
from statfit.registration.many import register_many
from statfit.core.stages import Fit

__all__ = ["StatModel", "load_model", "model_from_arrays", "save_model", "import_model", "build_model",
           "build_model_from_files", "register", "register_many", "reconstruct", "reconstruct_many", "Fit",
           "StatfitError", "DivergenceError", "__version__"]
