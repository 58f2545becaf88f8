"""Splat files (statfit/io/splats.py) and multi-view folders (statfit/io/views.py): round trips,
and one clear refusal for each kind of bad file."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from statfit.structures.camera import Camera
from statfit.errors import StatfitError
from statfit.io import views
from statfit.io.image import write_image
from statfit.io import splats as splat_io
from statfit.io.splats import RECORD
from statfit.splat.job import splat_records, splats_from_records


def splats_bytes(splats, vertices):
    return splat_io.splats_bytes(splat_records(splats, vertices), len(splats.faces))


def read_splats(path, faces, dtype=torch.float32):
    return splats_from_records(splat_io.read_splats(path, len(faces)), faces, dtype)
from statfit.io.views import CAMERAS_FILE, read_views, views_json
from statfit.renderer.binding import MeshSplats

VERTICES = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
FACES = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
WIDTH, HEIGHT = 8, 6


# --- splats -------------------------------------------------------------------------------------

def random_splats(seed: int = 0) -> MeshSplats:
    """3 splats per tetrahedron face with random free values, float64."""
    splats = MeshSplats.on(FACES, per_triangle=3, dtype=torch.float64)
    generator = torch.Generator().manual_seed(seed)
    count = len(splats)

    def leaf(*shape: int, scale: float) -> torch.Tensor:
        return ((torch.rand(*shape, generator=generator, dtype=torch.float64) - 0.5) * 2 * scale).requires_grad_(True)

    return MeshSplats(FACES, splats.triangle, splats.barycentric, leaf(count, scale=3.0), leaf(count, 2, scale=1.0),
                      leaf(count, 3, scale=4.0), leaf(count, scale=4.0))


def splat_file(tmp_path: Path, data: bytes | None = None) -> Path:
    path = tmp_path / "splats.ply"
    path.write_bytes(splats_bytes(random_splats(), VERTICES) if data is None else data)
    return path


def test_splats_round_trip(tmp_path):
    original = random_splats()
    read = read_splats(splat_file(tmp_path), FACES, dtype=torch.float64)
    assert torch.equal(read.triangle, original.triangle) and read.faces is FACES
    assert torch.equal(read.barycentric, original.barycentric.float().double())
    assert torch.equal(read.angle, original.angle.detach().float().double())
    assert torch.equal(read.log_scale, original.log_scale.detach().float().double())
    for name in ("colour_logit", "opacity_logit"):
        assert torch.allclose(getattr(read, name), getattr(original, name).detach(), atol=1e-4)
    for tensor in read.parameters().values():
        assert tensor.is_leaf and tensor.requires_grad and tensor.dtype == torch.float64
    vertices = torch.as_tensor(VERTICES)
    with torch.no_grad():
        mine, theirs = read.surfels(vertices), original.surfels(vertices)
    for name in ("centres", "tangent_u", "tangent_v", "scales", "colours", "opacity"):
        assert torch.allclose(getattr(mine, name), getattr(theirs, name), atol=1e-5), name


def test_splats_open_as_a_point_cloud(tmp_path):
    cloud = trimesh.load(splat_file(tmp_path))
    assert isinstance(cloud, trimesh.PointCloud) and len(cloud.vertices) == len(random_splats())
    with torch.no_grad():
        assert np.allclose(cloud.vertices, random_splats().surfels(torch.as_tensor(VERTICES)).centres.numpy(),
                           atol=1e-6)


def test_splats_refuse_other_than_rgb(tmp_path):
    splats = MeshSplats.on(FACES, channels=1)
    with pytest.raises(StatfitError, match="RGB splats; these have 1 colour channels"):
        splats_bytes(splats, VERTICES)


def _edited_records(edit) -> bytes:
    """The splat file with ``edit(records)`` applied to its records."""
    data = splats_bytes(random_splats(), VERTICES)
    start = data.index(b"end_header\n") + len(b"end_header\n")
    records = np.frombuffer(data[start:], dtype=RECORD).copy()
    edit(records)
    return data[:start] + records.tobytes()


def _set(name: str, value: float):
    def edit(records: np.ndarray) -> None:
        records[name][1] = value
    return edit


GOOD = splats_bytes(random_splats(), VERTICES)


@pytest.mark.parametrize("data, message", [
    (GOOD[:-10], r"declares 12 splats \(816 bytes\) but holds 806 bytes"),
    (GOOD.replace(b"element vertex 12", b"element vertex 1000000000"), "declares 1,000,000,000 splats"),
    (GOOD.replace(b"property float angle", b"property float angel"), "expected one 'element vertex' with the "
                                                                     "properties float x, .*int triangle"),
    (GOOD.replace(b"property int triangle", b"property float triangle"), "not a statfit splat file"),
    (GOOD.replace(b"end_header", b"element face 0\nend_header"), "not a statfit splat file"),
    (GOOD.replace(b"binary_little_endian", b"binary_big_endian"), "binary little-endian PLY"),
    (GOOD.replace(b"comment statfit", b"comment other"), "does not say which mesh"),
    (GOOD.replace(b"end_header\n", b"end_head\n"), "not a PLY file"),
    (b"", "is empty"),
    (_edited_records(_set("triangle", 4)), r"triangle indices must lie in \[0, 4\), got 0..4"),
    (_edited_records(_set("triangle", -1)), "triangle indices must lie in"),
    (_edited_records(_set("angle", np.nan)), "angle has NaN or infinite values"),
    (_edited_records(_set("f_green", 1.5)), r"f_green must lie in \[0, 1\]"),
    (_edited_records(_set("opacity", -0.5)), r"opacity must lie in \[0, 1\]"),
], ids=["truncated", "huge count", "property renamed", "property type", "extra element", "big endian",
        "no mesh comment", "no end_header", "empty", "triangle too big", "triangle negative", "nan",
        "colour above 1", "opacity below 0"])
def test_splats_refusals(tmp_path, data, message):
    with pytest.raises(StatfitError, match=message):
        read_splats(splat_file(tmp_path, data), FACES)


def test_splats_refuse_another_mesh(tmp_path):
    with pytest.raises(StatfitError, match="splats.ply was made for a mesh with 4 faces; this mesh has 3"):
        read_splats(splat_file(tmp_path), FACES[:3])


def test_splats_refuse_a_missing_file(tmp_path):
    with pytest.raises(StatfitError, match="splat file not found"):
        read_splats(tmp_path / "none.ply", FACES)


# --- views --------------------------------------------------------------------------------------

def camera(index: int, width: int = WIDTH, height: int = HEIGHT) -> Camera:
    angle = 2 * np.pi * index / 3
    return Camera.look_at([3 * np.sin(angle), 0.5, 3 * np.cos(angle)], [0, 0, 0], [0, 1, 0], 40.0, width, height)


def rgba(seed: int, visible: bool = True) -> np.ndarray:
    """An 8-bit-exact RGBA image (H, W, 4) whose left half is opaque (none of it unless ``visible``)."""
    image = np.round(np.random.default_rng(seed).random((HEIGHT, WIDTH, 4)) * 255) / 255
    image[..., 3] = 0.0
    image[:, : WIDTH // 2, 3] = 1.0 if visible else 0.0
    return image


def write_folder(folder: Path, splits=("train", "train", "test")) -> dict:
    """Three RGBA views in ``folder``; returns the cameras.json content (a dict to edit)."""
    folder.mkdir(exist_ok=True)
    for index in range(len(splits)):
        write_image(folder / f"view_{index:03d}.png", rgba(index))
    data = views_json([(f"view_{i:03d}.png", camera(i), split) for i, split in enumerate(splits)], gt="gt.ply")
    (folder / CAMERAS_FILE).write_bytes(data)
    return json.loads(data)


def rewrite(folder: Path, data) -> None:
    (folder / CAMERAS_FILE).write_text(json.dumps(data))


def test_views_round_trip(tmp_path):
    data = write_folder(tmp_path)
    assert data["format"] == "statfit-views" and data["version"] == 1 and data["gt"] == "gt.ply"
    assert (tmp_path / CAMERAS_FILE).read_bytes().endswith(b"}\n")
    read = read_views(tmp_path)
    assert [view.name for view in read] == ["view_000.png", "view_001.png", "view_002.png"]
    assert [view.split for view in read] == ["train", "train", "test"]
    for index, view in enumerate(read):
        assert view.image.dtype == np.float32 and view.image.shape == (HEIGHT, WIDTH, 3)
        assert np.allclose(view.image, rgba(index)[..., :3], atol=1e-6)
        assert view.mask.dtype == bool and np.array_equal(view.mask, rgba(index)[..., 3] > 0.5)
        assert view.camera.to_dict() == camera(index).to_dict()


def test_views_grey_rgb_and_mask_files(tmp_path):
    data = write_folder(tmp_path)
    write_image(tmp_path / "view_000.png", rgba(0)[..., :1])
    write_image(tmp_path / "view_001.png", rgba(1)[..., :3])
    mask = np.zeros((HEIGHT, WIDTH, 1))
    mask[0, 0] = 1.0
    write_image(tmp_path / "mask.png", mask)
    data["views"][2]["mask"] = "mask.png"
    rewrite(tmp_path, data)
    grey, rgb, masked = read_views(tmp_path)
    assert np.allclose(grey.image, rgba(0)[..., :1].repeat(3, axis=-1), atol=1e-6) and grey.mask is None
    assert np.allclose(rgb.image, rgba(1)[..., :3], atol=1e-6) and rgb.mask is None
    assert np.array_equal(masked.mask, mask[..., 0] > 0.5)  # the mask file wins over the alpha


def test_views_split_defaults_to_train(tmp_path):
    data = write_folder(tmp_path)
    for entry in data["views"]:
        del entry["split"]
    rewrite(tmp_path, data)
    assert [view.split for view in read_views(tmp_path)] == ["train"] * 3


def test_views_refuse_a_missing_folder(tmp_path):
    with pytest.raises(StatfitError, match="views folder not found"):
        read_views(tmp_path / "none")


def test_views_refuse_a_file_as_folder(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(StatfitError, match="views folder is not a folder"):
        read_views(tmp_path / "file")


def test_views_refuse_a_missing_cameras_file(tmp_path):
    with pytest.raises(StatfitError, match="views file not found: .*cameras.json"):
        read_views(tmp_path)


@pytest.mark.parametrize("text, message", [
    ("", "cameras.json is empty"),
    ("{views: []", "cameras.json is not valid JSON"),
    ("[" * 100_000, "cameras.json is not valid JSON"),
    ("[1, 2]", 'must be a JSON object with a "views" list'),
    ('{"format": "statfit-views"}', 'must be a JSON object with a "views" list'),
    ('{"views": {}}', 'must be a JSON object with a "views" list'),
    ('{"format": "other", "views": [{}]}', 'expected "format": "statfit-views", "version": 1'),
    ('{"views": []}', "cameras.json has no views"),
    (json.dumps({"views": [{}] * 1001}), "has 1,001 views; statfit reads at most 1,000"),
    ('{"views": [3]}', "view 0 is not a JSON object"),
    ('{"views": [{"image": "a.png"}]}', "view 0 lacks camera"),
    ('{"views": [{"camera": {}}]}', "view 0 lacks image"),
])
def test_views_refuse_bad_json(tmp_path, text, message):
    (tmp_path / CAMERAS_FILE).write_text(text)
    with pytest.raises(StatfitError, match=message):
        read_views(tmp_path)


def test_views_refuse_a_cameras_file_too_big(tmp_path, monkeypatch):
    write_folder(tmp_path)
    monkeypatch.setattr(views, "MAX_JSON_BYTES", 1000)
    with pytest.raises(StatfitError, match="cameras.json is larger than"):
        read_views(tmp_path)


def test_views_refuse_a_bad_camera(tmp_path):
    data = write_folder(tmp_path)
    data["views"][1]["camera"]["K"] = [[1, 0, 0], [0, 1, 0], [0, 0, 0]]
    rewrite(tmp_path, data)
    with pytest.raises(StatfitError, match="view view_001.png: camera K must have bottom row"):
        read_views(tmp_path)


@pytest.mark.parametrize("name", ["/etc/passwd", "../outside.png", "sub/../../outside.png"])
def test_views_refuse_names_outside_the_folder(tmp_path, name):
    folder = tmp_path / "views"
    data = write_folder(folder)
    write_image(tmp_path / "outside.png", rgba(0))
    data["views"][0]["image"] = name
    rewrite(folder, data)
    with pytest.raises(StatfitError, match="is not a file name inside the folder"):
        read_views(folder)


def test_views_refuse_a_mask_outside_the_folder(tmp_path):
    folder = tmp_path / "views"
    data = write_folder(folder)
    write_image(tmp_path / "outside.png", rgba(0))
    data["views"][0]["mask"] = "../outside.png"
    rewrite(folder, data)
    with pytest.raises(StatfitError, match="view view_000.png: '../outside.png' is not a file name inside"):
        read_views(folder)


def test_views_refuse_a_missing_image(tmp_path):
    write_folder(tmp_path)
    (tmp_path / "view_001.png").unlink()
    with pytest.raises(StatfitError, match="image not found: .*view_001.png"):
        read_views(tmp_path)


def test_views_refuse_an_unreadable_image(tmp_path):
    write_folder(tmp_path)
    (tmp_path / "view_001.png").write_bytes(b"not a png")
    with pytest.raises(StatfitError, match="cannot read image .*view_001.png"):
        read_views(tmp_path)


def test_views_refuse_an_image_of_another_size_than_its_camera(tmp_path):
    write_folder(tmp_path)
    write_image(tmp_path / "view_002.png", np.ones((5, 5, 3)))
    with pytest.raises(StatfitError, match="view view_002.png: the image is 5×5 but its camera 8×6"):
        read_views(tmp_path)


def test_views_refuse_views_of_different_sizes(tmp_path):
    data = write_folder(tmp_path)
    write_image(tmp_path / "view_001.png", np.ones((HEIGHT, WIDTH + 1, 3)))
    data["views"][1]["camera"] = camera(1, WIDTH + 1).to_dict()
    rewrite(tmp_path, data)
    with pytest.raises(StatfitError, match="all views must have the same size; view view_001.png is 9×6"):
        read_views(tmp_path)


def test_views_refuse_an_unknown_split(tmp_path):
    data = write_folder(tmp_path)
    data["views"][2]["split"] = "validation"
    rewrite(tmp_path, data)
    with pytest.raises(StatfitError, match="view view_002.png: split must be 'train' or 'test', got 'validation'"):
        read_views(tmp_path)


def test_views_refuse_no_train_view(tmp_path):
    write_folder(tmp_path, splits=("test", "test"))
    with pytest.raises(StatfitError, match="no view has split 'train'"):
        read_views(tmp_path)


def test_views_refuse_an_empty_alpha_mask(tmp_path):
    write_folder(tmp_path)
    write_image(tmp_path / "view_001.png", rgba(1, visible=False))
    with pytest.raises(StatfitError, match="view view_001.png: the mask is empty"):
        read_views(tmp_path)


def test_views_refuse_an_empty_mask_file(tmp_path):
    data = write_folder(tmp_path)
    write_image(tmp_path / "mask.png", np.zeros((HEIGHT, WIDTH, 1)))
    data["views"][0]["mask"] = "mask.png"
    rewrite(tmp_path, data)
    with pytest.raises(StatfitError, match="view view_000.png: the mask is empty"):
        read_views(tmp_path)


def test_views_refuse_a_mask_of_another_size(tmp_path):
    data = write_folder(tmp_path)
    write_image(tmp_path / "mask.png", np.ones((3, 3, 1)))
    data["views"][0]["mask"] = "mask.png"
    rewrite(tmp_path, data)
    with pytest.raises(StatfitError, match="view view_000.png: the mask is 3×3 but the image 8×6"):
        read_views(tmp_path)
