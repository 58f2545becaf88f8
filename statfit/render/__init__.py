"""Differentiable triangle rasterisation in pure torch (CPU and CUDA) with silhouette gradients.

``rasterize`` → ``Fragments`` (z-buffer ids, differentiable perspective-correct barycentrics),
``interpolate`` vertex attributes, ``antialias`` (or ``silhouette_crossings(...).blend``) for
gradients at silhouettes, ``render_normals`` for the whole chain (normal map and mask).
"""
from statfit.render.silhouette import EdgeCrossings, MeshAdjacency, antialias, silhouette_crossings
from statfit.camera import Camera
from statfit.render.raster import Fragments, interpolate, interpolate_fragments, rasterize
from statfit.render.shading import fragment_normals, normal_image, render_normals, vertex_normals

__all__ = ["Camera", "EdgeCrossings", "Fragments", "MeshAdjacency", "antialias", "interpolate",
           "fragment_normals", "interpolate_fragments", "normal_image", "rasterize", "render_normals", "silhouette_crossings",
           "vertex_normals"]
