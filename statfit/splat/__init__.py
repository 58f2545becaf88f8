"""The ``statfit splat`` job: photographs → a mesh with Gaussian splats bound to its triangles.

- :mod:`statfit.splat.job`: the fit (:func:`~statfit.splat.job.splat`).
- :mod:`statfit.splat.preview`: the held-out view's preview picture.
"""
