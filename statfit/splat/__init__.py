"""Gaussian splatting on meshes: 2D Gaussian surfels (:mod:`statfit.splat.raster`) bound to a
mesh's triangles (:mod:`statfit.splat.binding`)."""
from statfit.splat.binding import MeshSplats
from statfit.splat.raster import SplatImage, Surfels, render_surfels

__all__ = ["MeshSplats", "SplatImage", "Surfels", "render_surfels"]
