"""How a render fit's start sits in the map's image: the map's foreground, the frame of its normals,
the model's units and side of the camera, an initial mesh."""
from __future__ import annotations

import numpy as np

from statfit.core.runaway import image_ratio
from statfit.errors import StatfitError
from statfit.model.statmodel import StatModel
from statfit.renderer import Camera
from statfit.structures.frame import UNIT_MISMATCH_FACTOR, Frame
from statfit.structures.normal_map import NormalMap

MIN_FOREGROUND = 16        # a map's foreground pixels, at least
NORMAL_SPACES = ("world", "camera")
NORMAL_CONVENTIONS = ("opencv", "opengl")
# A visible surface's normals face the camera. Read in their own frame, synthetic maps of the embedded
# and ICT heads (96² to 512²) do on 99-100% of their foreground; world-space ones read as OpenCV camera
# space on 2%; seen nearly from the front, world and OpenGL camera space are alike (93-95%). A map
# whose normals face the camera on less than FACING_MIN is refused, naming the frames in which they
# face it on FACING_OTHER or more.
FACING_MIN = 0.5
FACING_OTHER = 0.8
FRAMES = (("world", "opencv"), ("camera", "opencv"), ("camera", "opengl"))


def camera_space_normals(normal_map: NormalMap, camera: Camera, space: str = "world",
                         convention: str = "opencv") -> np.ndarray:
    """The map's normals (H, W, 3) in camera space with OpenCV axes (x right, y down, z forward).

    space 'world': normals in the camera's world frame; 'camera' with convention 'opencv', or
    'opengl' (x right, y up, z towards the viewer)."""
    if space not in NORMAL_SPACES:
        raise StatfitError(f"unknown normal space {space!r}; choose world or camera")
    if convention not in NORMAL_CONVENTIONS:
        raise StatfitError(f"unknown normal convention {convention!r}; choose opencv or opengl")
    normals = normal_map.normals.astype(np.float64)
    if space == "world":
        normals = normals @ camera.rotation.numpy().T
    elif convention == "opengl":
        normals = normals * np.array([1.0, -1.0, -1.0])
    return np.where(normal_map.mask[..., None], normals, 0.0)


def facing_share(normals: np.ndarray, mask: np.ndarray, camera: Camera) -> float:
    """The share of the foreground ``mask`` (H, W) whose camera-space normals ``normals`` (H, W, 3)
    (OpenCV axes) face the camera: n · ray < 0 for the ray through the pixel's centre."""
    rows, cols = np.nonzero(mask)
    pixels = np.stack([cols + 0.5, rows + 0.5, np.ones(len(rows))], axis=1)
    rays = pixels @ np.linalg.inv(camera.K.numpy().astype(np.float64)).T
    return float(((normals[rows, cols] * rays).sum(axis=1) < 0).mean())


def check_normals_face_camera(normals: np.ndarray, normal_map: NormalMap, camera: Camera, space: str,
                              convention: str) -> None:
    """Refuse a map whose normals, read in the frame ``space`` / ``convention`` as ``normals``
    (H, W, 3) in camera space, face away from the camera: a map in another frame than the one
    declared (the refusal names the frames in which they face it)."""
    share = facing_share(normals, normal_map.mask, camera)
    if share >= FACING_MIN:
        return
    declared = (space, convention if space == "camera" else "opencv")
    others = [frame for frame in FRAMES if frame != declared and facing_share(
        camera_space_normals(normal_map, camera, *frame), normal_map.mask, camera) >= FACING_OTHER]
    advice = ("read as " + " or ".join(f"{_frame_name(*frame)} normals ({_flags(*frame)})" for frame in others)
              + " they face it" if others else "check --normal-space and --normal-convention")
    raise StatfitError(f"the normal map's normals face away from the camera on {1 - share:.0%} of its foreground "
                       f"read as {_frame_name(*declared)} normals; {advice}")


def _flags(space: str, convention: str) -> str:
    return f"--normal-space {space}" + (f" --normal-convention {convention}" if space == "camera" else "")


def _frame_name(space: str, convention: str) -> str:
    return "world-space" if space == "world" else f"camera-space ({'OpenCV' if convention == 'opencv' else 'OpenGL'})"


def check_framing(template: np.ndarray, camera: Camera, mask: np.ndarray, align: str) -> None:
    """Refuse a mask with too few foreground pixels, a model behind the camera, or one whose image is
    far larger or smaller than the target's silhouette (units?) unless the alignment estimates a
    scale. ``template``: (M, 3) the start's vertices that triangles use (a vertex no face uses is
    never drawn, wherever it lies)."""
    if not mask.any():
        raise StatfitError("the normal map's mask has no foreground pixel")
    if (count := int(mask.sum())) < MIN_FOREGROUND:     # no surface, nor its size against the model's (units)
        raise StatfitError(f"the normal map shows {count} foreground pixel{'' if count == 1 else 's'}: too few (at least {MIN_FOREGROUND})")
    ratio = image_ratio(template, camera, mask)
    if align != "similarity" and not 1 / UNIT_MISMATCH_FACTOR < ratio < UNIT_MISMATCH_FACTOR:
        raise StatfitError(f"the model's image is {ratio:.3g} times the size of the normal map's silhouette: are the "
                           "model and the camera in different units? Rescale one, or use --align similarity")


def checked_init(init: np.ndarray, model: StatModel) -> np.ndarray:
    """The initial mesh ``init`` (N, 3) for ``model``, refused in one line unless it is the model's
    topology's, finite and of some extent."""
    init = np.asarray(init, dtype=np.float64)
    if init.shape != model.template.shape:
        raise StatfitError(f"the initial mesh has {init.shape[0]} vertices; the model has {model.num_vertices}")
    if not np.isfinite(init).all():
        raise StatfitError("the initial mesh has NaN or infinite coordinates")
    if not Frame.of(init, model.faces).scale > 1e-9 * model.frame.scale:
        raise StatfitError("the initial mesh's vertices all coincide: a mesh without extent")
    return init
