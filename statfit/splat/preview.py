"""The picture of a splatting fit: for one view, the photograph, the splats rendered at the fit,
their error, and the fitted mesh itself, shaded (what the splats hide)."""
from __future__ import annotations

import io

import numpy as np
from PIL import Image, ImageDraw

from statfit.structures.camera import Camera
from statfit.renderer import MeshSplats
from statfit.splat.job import render_splats
from statfit.renderer.images import photograph

ERROR_GAIN = 4.0   # the error panel shows |splats − photograph| × 4
MESH_GREY = 0.8


def splat_preview_png(photo: np.ndarray, splats: MeshSplats, vertices: np.ndarray, faces: np.ndarray,
                      camera: Camera, label: str) -> bytes:
    """A PNG row of four panels, each titled: ``photo`` (H, W, 3), the splats on ``vertices``
    (N, 3) seen by ``camera``, the error, the mesh shaded in grey."""
    rendered, _ = render_splats(splats, vertices, camera)
    error = np.clip(np.abs(rendered - photo).mean(axis=-1, keepdims=True) * ERROR_GAIN, 0, 1) * [1.0, 0.35, 0.1]
    mesh, _ = photograph(vertices, faces, np.full((len(vertices), 3), MESH_GREY), camera)
    panels = [(f"photograph ({label})", photo), ("splats on the fit", rendered), ("|error| x 4", error),
              ("fitted mesh", mesh)]
    height, width = photo.shape[:2]
    scale = max(1, 256 // max(height, width))
    title = 18
    canvas = Image.new("RGB", (len(panels) * width * scale, height * scale + title), "white")
    draw = ImageDraw.Draw(canvas)
    for index, (name, image) in enumerate(panels):
        tile = Image.fromarray(np.round(np.clip(image, 0, 1) * 255).astype(np.uint8))
        canvas.paste(tile.resize((width * scale, height * scale), Image.NEAREST), (index * width * scale, title))
        draw.text((index * width * scale + 4, 3), name, fill="black")
    buffer = io.BytesIO()
    canvas.save(buffer, format="PNG")
    return buffer.getvalue()
