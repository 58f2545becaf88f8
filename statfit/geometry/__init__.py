"""Geometry on arrays: similarity transforms and ICP (:mod:`~statfit.geometry.align`), closest
points on a mesh (:mod:`~statfit.geometry.closest`), and a fit's errors
(:mod:`~statfit.geometry.metrics`)."""
