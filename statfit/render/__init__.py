"""The ``statfit render`` job: a model's template fitted to one normal map (inverse rendering).

- :mod:`statfit.render.job`: the fit (:func:`~statfit.render.job.reconstruct`).
- :mod:`statfit.render.preview`: the preview picture (target, fit, error, side and back views).

The rasteriser itself is shared with other jobs and lives in :mod:`statfit.renderer`.
"""
