"""The ``statfit register`` job: a model's template fitted to a 3D scan.

- :mod:`statfit.register.job`: the entry point (:func:`~statfit.register.job.register`).
- :mod:`statfit.register.pose`: the automatic pose, scale and units (no landmarks needed).
- :mod:`statfit.register.hair`: which scan points are hair or clutter, not the head.
"""
