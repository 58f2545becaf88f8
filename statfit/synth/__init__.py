"""Synthetic data with a known ground truth: the inputs of ``statfit synth``.

- :mod:`statfit.synth.sample`: model samples, partial scans and the cameras of normal maps.
- :mod:`statfit.synth.scanner`: a range scanner's mesh (hair, neck, any pose, units).
- :mod:`statfit.synth.views`: photographs from many cameras, for ``statfit splat``.
"""
