"""The ``statfit register`` job: a model's template fitted to a 3D scan.

- :mod:`statfit.registration.job`: the entry point (:func:`~statfit.registration.job.register`).
- :mod:`statfit.registration.many`: many scans in one program, their gradient stages stepped
  together (:func:`~statfit.registration.many.register_many`; ``statfit batch register --together``).
- :mod:`statfit.registration.posed`: a scan placed on the model, ready for fits; the options checked.
- :mod:`statfit.registration.prealign`: the scan checked and placed (pose search, landmarks, ICP).
- :mod:`statfit.registration.pose`: the automatic pose, scale and units (no landmarks needed).
- :mod:`statfit.registration.hair`: which scan points are hair or clutter, not the head.
- :mod:`statfit.registration.preview`: the preview picture (the scan on the fit; where the fit guessed).
"""
