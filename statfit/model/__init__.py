"""Statistical shape models: the model and its regions (:mod:`~statfit.model.statmodel`), building
one by PCA (:mod:`~statfit.model.build`, :mod:`~statfit.model.pca`) and importing other formats
(:mod:`~statfit.model.importers`)."""
