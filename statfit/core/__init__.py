"""The fitting core, shared by every job: gradient filters and their solvers, parametrisations,
UniformAdam, the loop (:mod:`~statfit.core.fit`), the stage runner, the method registry and its
settings, the Gauss–Newton coefficient solve, gradient-based pose, threads and devices.

The core never reads or writes files (``tests/test_layering.py``)."""
