"""Texture inpainting: the gradient filters on an image grid, texture PCA models, the fit."""
