"""statfit: fit a template mesh to limited observations with statistical gradient filtering."""
__version__ = "0.1.0"

from statfit.errors import DivergenceError, StatfitError
from statfit.model import StatModel, load_model, model_from_arrays
from statfit.inverse_render import Reconstruction, reconstruct
from statfit.register import Registration, register

__all__ = ["StatModel", "load_model", "model_from_arrays", "register", "Registration", "reconstruct", "Reconstruction",
           "StatfitError", "DivergenceError", "__version__"]
