"""The ``statfit register`` job: a model's template fitted to a 3D scan.

- :mod:`statfit.registration.job`: the entry point (:func:`~statfit.registration.job.register`).
- :mod:`statfit.registration.pose`: the automatic pose, scale and units (no landmarks needed).
- :mod:`statfit.registration.hair`: which scan points are hair or clutter, not the head.
"""
