"""Texture PCA models: a texture is a "template" of H·W vertices with C channels.

npz contract (docs/formats.md): ``v_template (H·W, C)`` the mean texture, pixels row-major;
``shapedirs (H·W, C, K)`` directions of any scale (a texture is ``v_template + shapedirs @ c``,
c ~ N(0, I)); ``image_size = [H, W]``; ``kind = "texture"``. No ``faces``: the pixel grid is the
topology. Flattened, entry ``p·C + c`` is channel c of pixel p, the order of ``image.reshape(-1)``.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from statfit.errors import StatfitError
from statfit.io.files import write_atomic
from statfit.io.npz import npz_bytes, read_npz
from statfit.model.statmodel import _float_array
from statfit.model.pca import principal_components, with_fixed_signs
from statfit.errors import StatfitWarning
from statfit.texture.resample import resize_image

# Modes whose variance is below this fraction of the first's are dropped on loading (the Gram
# matrix squares the condition number, so smaller ones are rounding noise).
MIN_VARIANCE_RATIO = 1e-12
GRAM_ROWS = 1 << 18  # rows of shapedirs per block when forming the Gram matrix in float64


@dataclass(frozen=True)
class TextureModel:
    """mean (H·W, C) float32; basis_t (K, H·W·C) float32 orthonormal rows; std (K,) decreasing."""

    mean: np.ndarray
    basis_t: np.ndarray
    std: np.ndarray
    height: int
    width: int
    source: str = "<arrays>"

    @property
    def channels(self) -> int:
        return self.mean.shape[1]

    @property
    def num_modes(self) -> int:
        return self.basis_t.shape[0]

    @property
    def size(self) -> tuple[int, int]:
        return self.height, self.width

    def texture(self, coeffs: np.ndarray) -> np.ndarray:
        """The texture (H, W, C) for coefficients in standard-deviation units, (K,)."""
        flat = self.mean.reshape(-1) + (np.asarray(coeffs, dtype=np.float64) * self.std) @ self.basis_t
        return flat.reshape(self.height, self.width, self.channels).astype(np.float32)

    def npz_arrays(self) -> dict[str, np.ndarray]:
        """The model in the npz contract (float32 arrays)."""
        shapedirs = (self.basis_t * self.std[:, None].astype(np.float32)).T
        return {"v_template": self.mean.astype(np.float32),
                "shapedirs": np.ascontiguousarray(shapedirs).reshape(self.height * self.width, self.channels, -1),
                "image_size": np.array([self.height, self.width], dtype=np.int64), "kind": np.array("texture")}

    def save(self, path: str | Path) -> None:
        """Write the model npz atomically."""
        write_atomic(path, npz_bytes(self.npz_arrays()))


def texture_model_from_arrays(v_template: np.ndarray, shapedirs: np.ndarray, image_size: np.ndarray,
                              source: str = "<arrays>") -> TextureModel:
    """Validate contract arrays and derive the orthonormal basis from the Gram matrix of
    ``shapedirs`` (K × K, formed blockwise in float64: cheap for the tall matrices of textures).
    Each direction's sign is fixed as in :func:`statfit.model.pca.principal_components`."""
    size = np.asarray(image_size).reshape(-1)
    if size.size != 2 or not np.issubdtype(size.dtype, np.integer) or (size < 1).any():
        raise StatfitError(f"{source}: image_size must be two positive integers [H, W], got {size.tolist()}")
    height, width = int(size[0]), int(size[1])
    mean = _float_array(v_template, f"{source}: v_template")
    if mean.ndim != 2 or mean.shape[0] != height * width or not 1 <= mean.shape[1] <= 4:
        raise StatfitError(f"{source}: v_template must have shape ({height * width}, C) with C in 1..4, "
                           f"got {mean.shape}")
    shapedirs = np.asarray(shapedirs)
    if shapedirs.ndim != 3 or shapedirs.shape[:2] != mean.shape or shapedirs.shape[2] == 0:
        raise StatfitError(f"{source}: shapedirs must have shape ({mean.shape[0]}, {mean.shape[1]}, K), "
                           f"got {shapedirs.shape}")
    flat = shapedirs.reshape(-1, shapedirs.shape[2])
    gram = np.zeros((flat.shape[1], flat.shape[1]))
    for start in range(0, flat.shape[0], GRAM_ROWS):
        block = _float_array(flat[start:start + GRAM_ROWS], f"{source}: shapedirs")
        gram += block.T @ block
    variance, vectors = np.linalg.eigh(gram)
    variance, vectors = variance[::-1], vectors[:, ::-1]
    if variance[0] <= 0:
        raise StatfitError(f"{source}: shapedirs are all zero")
    keep = variance > variance[0] * MIN_VARIANCE_RATIO
    std = np.sqrt(variance[keep])
    # (K, D) directly: flat.T is a view, so the tall shapedirs are not copied.
    basis_t = (vectors[:, keep] / std).T.astype(np.float32) @ np.asarray(flat, dtype=np.float32).T
    return TextureModel(mean.astype(np.float32), with_fixed_signs(basis_t), std, height, width, source)


def load_texture_model(path: str | Path) -> TextureModel:
    """Load and validate a texture model npz."""
    arrays = read_npz(path, "texture model")
    if "image_size" not in arrays:
        raise StatfitError(f"{path} is not a texture model (no image_size); build one with "
                           "`statfit model build-texture`")
    missing = [key for key in ("v_template", "shapedirs") if key not in arrays]
    if missing:
        raise StatfitError(f"texture model {path} lacks the key(s) {', '.join(missing)}")
    return texture_model_from_arrays(arrays["v_template"], arrays["shapedirs"], arrays["image_size"], str(path))


def jitter_colours(images: np.ndarray, copies: int, rng: np.random.Generator) -> np.ndarray:
    """``copies`` colour-jittered versions of each image of ``images`` (M, H, W, C), (M·copies, H, W, C).

    Per copy: brightness × U(0.8, 1.2); contrast × U(0.8, 1.2) about the image's mean grey; a
    gain U(0.9, 1.1) per colour channel (a hue/white-balance shift); clipped to [0, 1]. Alpha is kept.
    """
    m, _, _, c = images.shape
    colour = min(c, 3)
    base = np.repeat(images, copies, axis=0)
    n = base.shape[0]
    brightness = rng.uniform(0.8, 1.2, (n, 1, 1, 1))
    contrast = rng.uniform(0.8, 1.2, (n, 1, 1, 1))
    gains = rng.uniform(0.9, 1.1, (n, 1, 1, colour))
    rgb = base[..., :colour]
    grey = rgb.mean(axis=(1, 2, 3), keepdims=True)
    rgb = ((rgb - grey) * contrast + grey) * brightness * gains
    base[..., :colour] = np.clip(rgb, 0.0, 1.0)
    return base


def as_channels(image: np.ndarray, channels: int, source: str) -> np.ndarray:
    """``image`` (H, W, C) with ``channels`` channels: grey → RGB by copying, RGB → RGBA with opaque
    alpha; anything else is an error."""
    c = image.shape[-1]
    if c == channels:
        return image
    if c == 1 and channels in (3, 4):
        image = np.repeat(image, 3, axis=-1)
    if image.shape[-1] == 3 and channels == 4:
        return np.concatenate([image, np.ones_like(image[..., :1])], axis=-1)
    if image.shape[-1] != channels:
        raise StatfitError(f"{source} has {c} channel(s) but {channels} are needed")
    return image


def build_texture_model(images: Iterable[tuple[str, np.ndarray]], size: tuple[int, int], k: int, *,
                        jitter: int = 0, seed: int = 0, randomized: bool | None = None) -> TextureModel:
    """PCA texture model from ``(name, image (H, W, C))`` pairs: each resized to ``size`` (H, W),
    all promoted to the largest channel count, ``jitter`` colour-jittered copies added per image
    (:func:`jitter_colours`), then :func:`statfit.model.pca.principal_components` with ``k`` modes (fewer,
    with a warning, when there are not enough samples)."""
    resized = [(name, resize_image(image, size)) for name, image in images]
    if len(resized) < 2:
        raise StatfitError(f"a texture model needs at least 2 images, got {len(resized)}")
    channels = max(image.shape[-1] for _, image in resized)
    stack = np.stack([as_channels(image, channels, name) for name, image in resized])
    rng = np.random.default_rng(seed)
    if jitter > 0:
        stack = np.concatenate([stack, jitter_colours(stack, jitter, rng)])
    if k > len(stack) - 1:
        warnings.warn(f"{len(stack)} samples give at most {len(stack) - 1} modes; keeping {len(stack) - 1}",
                      StatfitWarning)
        k = len(stack) - 1
    pca = principal_components(stack.reshape(stack.shape[0], -1), k, randomized=randomized, seed=seed)
    return TextureModel(pca.mean.reshape(-1, channels).astype(np.float32), pca.directions.astype(np.float32),
                        pca.std, size[0], size[1])
