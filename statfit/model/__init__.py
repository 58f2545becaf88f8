"""Statistical shape models: the model and its regions (:mod:`~statfit.model.statmodel`), building
one by PCA (:mod:`~statfit.model.build`, :mod:`~statfit.model.pca`) and importing other formats
(:mod:`~statfit.model.importers`). The model's own names are re-exported here."""
from statfit.model.statmodel import (StatModel, default_model_path, face_triangles, load_model, model_from_arrays,
                                     region_triangles, region_vertices, save_model, scalp_triangles)

__all__ = ["StatModel", "default_model_path", "face_triangles", "load_model", "model_from_arrays",
           "region_triangles", "region_vertices", "save_model", "scalp_triangles"]
