"""Preview of an inpainting: input with its holes checkered | result | the model-only reconstruction
("no model" without one), labelled, as one PNG."""
from __future__ import annotations

import io

import numpy as np
from PIL import Image, ImageDraw

MIN_HEIGHT = 256   # small images are enlarged (nearest neighbour) to at least this height
GAP, LABEL = 8, 16  # pixels between panels, height of the label strip
CHECKER = 8         # checker square size in output pixels
HOLE_COLOURS = (np.array([1.0, 0.0, 1.0]), np.array([0.25, 0.25, 0.25]))


def _rgb(image: np.ndarray) -> np.ndarray:
    """(H, W, C) → (H, W, 3) in [0, 1]: grey repeated, alpha dropped."""
    rgb = np.repeat(image, 3, axis=-1) if image.shape[-1] == 1 else image[..., :3]
    return np.clip(rgb, 0.0, 1.0)


def _enlarged(rgb: np.ndarray, factor: int) -> np.ndarray:
    return np.repeat(np.repeat(rgb, factor, axis=0), factor, axis=1)


def preview_png(image: np.ndarray, visible: np.ndarray, result: np.ndarray, model_only: np.ndarray | None) -> bytes:
    """PNG bytes of the three panels for images (H, W, C) and the mask (H, W)."""
    height, width = visible.shape
    factor = max(1, -(-MIN_HEIGHT // height))
    rows, cols = np.indices((height * factor, width * factor))
    checker = ((rows // CHECKER + cols // CHECKER) % 2 == 0)[..., None]
    holes = np.where(checker, HOLE_COLOURS[0], HOLE_COLOURS[1])
    seen = _enlarged(visible[..., None], factor)
    panels = [np.where(seen, _enlarged(_rgb(image), factor), holes), _enlarged(_rgb(result), factor),
              _enlarged(_rgb(model_only), factor) if model_only is not None else np.full_like(holes, 0.5)]
    labels = ["input (holes checkered)", "result", "model only" if model_only is not None else "no model"]
    panel_w, panel_h = width * factor, height * factor
    canvas = Image.new("RGB", (3 * panel_w + 2 * GAP, panel_h + LABEL), "white")
    draw = ImageDraw.Draw(canvas)
    for i, (panel, label) in enumerate(zip(panels, labels)):
        left = i * (panel_w + GAP)
        canvas.paste(Image.fromarray(np.round(panel * 255).astype(np.uint8)), (left, LABEL))
        draw.text((left + 2, 2), label, fill="black")
    buffer = io.BytesIO()
    canvas.save(buffer, format="PNG")
    return buffer.getvalue()
