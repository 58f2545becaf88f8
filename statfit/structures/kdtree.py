"""KD-trees that build whatever the thread's floating-point mode.

statfit's fits and batch workers flush subnormal floats to zero (:mod:`statfit.core.threads`: faster
kernels). SciPy's balanced KD-tree build then recurses without end, and the process dies of a
segmentation fault, where many points tie at exactly zero on one axis (found with SciPy 1.17.1: a scan
with 1,500 of its 4,300 points on x = 0). :func:`kd_tree` builds with subnormals kept on the calling
thread and restores its mode: the same tree as a process that never flushed builds."""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

_SMALLEST_SUBNORMAL = np.array([5e-324])


def flushes_subnormals() -> bool:
    """Whether this thread treats subnormal floats as zero (a subnormal times 1 comes out 0)."""
    return bool((_SMALLEST_SUBNORMAL * 1.0)[0] == 0.0)


def kd_tree(points: np.ndarray, **options) -> cKDTree:
    """``scipy.spatial.cKDTree(points, **options)`` (points (M, D)), built with subnormals kept on
    this thread whatever its mode (module docstring)."""
    flushing = flushes_subnormals()
    if flushing:
        torch.set_flush_denormal(False)
    try:
        return cKDTree(points, **options)
    finally:
        if flushing:
            torch.set_flush_denormal(True)
