"""The differentiable renderers every job shares, in pure torch (CPU and CUDA).

Triangles: ``rasterize`` → ``Fragments`` (z-buffer ids, differentiable perspective-correct
barycentrics), ``interpolate`` vertex attributes, ``antialias`` (or
``silhouette_crossings(...).blend``) for gradients at silhouettes, ``render_normals`` for the whole
chain (normal map and mask). Splats: 2D Gaussian surfels (:mod:`statfit.renderer.surfels`) bound
to a mesh's triangles (:mod:`statfit.renderer.binding`).
"""
from statfit.renderer.silhouette import EdgeCrossings, MeshAdjacency, antialias, silhouette_crossings
from statfit.structures.camera import Camera
from statfit.renderer.raster import Fragments, interpolate, interpolate_fragments, rasterize
from statfit.renderer.shading import fragment_normals, normal_image, render_normals, vertex_normals
from statfit.renderer.binding import MeshSplats
from statfit.renderer.surfels import SplatImage, Surfels, render_surfels

__all__ = ["Camera", "EdgeCrossings", "Fragments", "MeshAdjacency", "MeshSplats", "SplatImage", "Surfels",
           "antialias", "interpolate", "fragment_normals", "interpolate_fragments", "normal_image", "rasterize",
           "render_normals", "render_surfels", "silhouette_crossings", "vertex_normals"]
