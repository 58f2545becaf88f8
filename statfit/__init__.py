"""statfit: fit a template mesh to limited observations with statistical gradient filtering."""
__version__ = "0.1.0"

from statfit.errors import DivergenceError, StatfitError
from statfit.model import StatModel, load_model, model_from_arrays, save_model
from statfit.importers import import_model
from statfit.build import build_model, build_model_from_files
from statfit.inverse_render import Reconstruction, reconstruct
from statfit.register import Registration, register

__all__ = ["StatModel", "load_model", "model_from_arrays", "save_model", "import_model", "build_model",
           "build_model_from_files", "register", "Registration", "reconstruct", "Reconstruction",
           "StatfitError", "DivergenceError", "__version__"]
