import json

import ml_collections
import numpy as np
import pytest
from PIL import Image

from conftest import LEGO, TINY_NPZ, require
from nerfpod import scenes
from nerfpod.errors import UserError
from nerfpod.nerf import cameras
from nerfpod.scenes import blender, procedural, street, tiny


@pytest.mark.parametrize("name", ["default", "street"])
def test_a_built_in_scene_is_traced_once_per_process_and_handed_out_read_only(name):
  """scenes.load of the same built-in scene gives the object it traced first, whose arrays no caller can write
  into (another caller holds them too); another size is another scene, traced from the same cameras."""
  from conftest import load_config
  data = load_config(name, "smoke").data
  first = scenes.load(data)
  assert scenes.load(data) is first
  train = first.split("train")
  for array in (train.pixels, train.poses, train.cameras.fx, first.transform):
    with pytest.raises(ValueError, match="read-only"):
      array[0] = 0
  data.image_size += 8
  bigger = scenes.load(data)
  assert bigger is not first and bigger.split("train").images.shape[1] == train.images.shape[1] + 8
  np.testing.assert_array_equal(bigger.split("train").poses, train.poses)


def test_procedural_scene_is_deterministic_and_shaped_like_blender_data():
  a, b = procedural.make(image_size=24), procedural.make(image_size=24)
  for name, n in (("train", 100), ("val", 8), ("test", 8)):
    np.testing.assert_array_equal(a.splits[name].images, b.splits[name].images)
    assert a.splits[name].images.shape == (n, 24, 24, 3)
  assert (a.near, a.far, a.background) == (2.0, 6.0, (1.0, 1.0, 1.0))
  images = np.asarray(a.splits["train"].images)
  assert (images == 1.0).all(-1).mean() > 0.2  # background visible
  assert (images < 0.9).any(-1).mean() > 0.2   # and the solids
  for pose in a.splits["train"].poses:
    eye = pose[:3, 3]
    np.testing.assert_allclose(np.linalg.norm(eye), 4.0, rtol=1e-5)
    assert eye[2] > 0  # upper hemisphere
    np.testing.assert_allclose(-pose[:3, 2], -eye / 4.0, atol=1e-5)  # looks at the origin
  assert not np.allclose(a.splits["train"].poses[:8], a.splits["test"].poses)  # held out is new


def test_procedural_ray_tracing_is_exact_for_a_ray_onto_the_sphere_top():
  centre = np.array([0.45, 0.35, 0.45])  # the red sphere's (radius 0.45): the ray hits its top point
  colour = procedural.trace(np.array([[centre[0], centre[1], 3.0]]), np.array([[0.0, 0.0, -1.0]]))[0]
  shade = procedural._AMBIENT + (1 - procedural._AMBIENT) * procedural._LIGHT[2]  # normal +z at the top
  np.testing.assert_allclose(colour, np.array([0.85, 0.2, 0.15]) * shade, rtol=1e-6)
  miss = procedural.trace(np.array([[5.0, 5.0, 5.0]]), np.array([[0.0, 0.0, 1.0]]))[0]
  np.testing.assert_array_equal(miss, 1.0)


def test_street_scene_is_deterministic_with_its_cameras_along_the_street_inside_the_box():
  a, b = street.make(image_size=16, num_train=12), street.make(image_size=16, num_train=12)
  for name, n in (("train", 12), ("val", 8), ("test", 8)):
    np.testing.assert_array_equal(a.splits[name].images, b.splits[name].images)
    assert a.splits[name].images.shape == (n, 16, 16, 3)
  assert (a.near, a.far, a.kind) == (street.NEAR, street.FAR, "street")
  eyes = np.concatenate([a.splits[name].poses[:, :3, 3] for name in a.splits])
  assert (np.abs(eyes[:, 0]) <= street.LENGTH / 2).all() and (np.abs(eyes[:, 1]) <= 1.0).all()
  assert ((eyes[:, 2] >= 0.8) & (eyes[:, 2] <= 1.6)).all()  # eye height, under the roofs
  # The cameras span the street: many times their spacing, which is what regions are cut along.
  xs = np.sort(street.make(image_size=4).splits["train"].poses[:, 0, 3])
  assert xs[-1] - xs[0] > 12.0 and np.median(np.diff(xs)) < 0.2
  alphas = np.asarray(a.splits["train"].alphas) / 255.0  # (kept as uint8)
  assert 0.3 < alphas.mean() < 0.9  # buildings and ground, and sky
  assert not np.allclose(a.splits["train"].poses[:8], a.splits["test"].poses)  # held out is new


def test_street_ray_tracing_is_exact_for_the_road_and_the_sky():
  # Straight down onto the road at (0.1, 0.1): the dark check of 0.25 (floor sum even -> light; here 0 + 0),
  # lit from above; straight up from the road: sky.
  down = street.trace(np.array([[0.1, 0.1, 2.0]]), np.array([[0.0, 0.0, -1.0]]), return_alpha=True)
  shade = procedural._AMBIENT + (1 - procedural._AMBIENT) * procedural._LIGHT[2]
  np.testing.assert_allclose(down[0][0], np.array([0.42, 0.42, 0.45]) * shade, rtol=1e-6)
  assert down[1][0] == 1.0
  other = street.trace(np.array([[0.35, 0.1, 2.0]]), np.array([[0.0, 0.0, -1.0]]))[0]
  np.testing.assert_allclose(other, np.array([0.25, 0.25, 0.28]) * shade, rtol=1e-6)
  up = street.trace(np.array([[0.1, 0.1, 0.5]]), np.array([[0.0, 0.0, 1.0]]), return_alpha=True)
  np.testing.assert_array_equal(up[0][0], 1.0)
  assert up[1][0] == 0.0


def test_tiny_nerf_loader_on_the_real_file():
  scene = tiny.read(str(require(TINY_NPZ)))
  train, test = scene.split("train"), scene.split("test")
  assert train.images.shape == (100, 100, 100, 3) and test.images.shape == (6, 100, 100, 3)
  assert train.intrinsics.fx == pytest.approx(138.8889, rel=1e-5)
  assert scene.background == (0.0, 0.0, 0.0)
  with np.load(TINY_NPZ) as npz:
    np.testing.assert_array_equal(test.poses, npz["poses"][100:])


def test_blender_loader_on_real_lego_with_downscale():
  scene = blender.read(str(require(LEGO)), downscale=4)
  train = scene.split("train")
  assert train.images.shape == (100, 100, 100, 3)
  with open(LEGO / "transforms_train.json") as f:
    meta = json.load(f)
  assert train.intrinsics.fx == pytest.approx(0.5 * 100 / np.tan(0.5 * meta["camera_angle_x"]))
  np.testing.assert_allclose(train.poses[3], np.array(meta["frames"][3]["transform_matrix"]), rtol=1e-6)
  np.testing.assert_allclose(train.images[:, 0, 0], 1.0)  # transparent corners composite to white
  assert set(scene.splits) == {"train", "val"}
  with pytest.raises(UserError, match="no 'test' split.*eval.split"):
    scene.split("test")


def _write_scene(root, size=8, frames=2, alpha=255, sizes=None):
  """A tiny Blender-format scene: `frames` solid red RGBA images."""
  (root / "train").mkdir(parents=True)
  meta = {"camera_angle_x": 0.69, "frames": []}
  for i in range(frames):
    s = (sizes or {}).get(i, size)
    Image.fromarray(np.tile(np.array([255, 0, 0, alpha], np.uint8), (s, s, 1))).save(root / "train" / f"r_{i}.png")
    pose = cameras.spherical_pose(30.0 * i, -30.0, 4.0)
    meta["frames"].append({"file_path": f"./train/r_{i}", "transform_matrix": pose.tolist()})
  (root / "transforms_train.json").write_text(json.dumps(meta))
  return meta


def test_blender_rgba_is_composited_on_white_then_box_downscaled(tmp_path):
  _write_scene(tmp_path, size=8, alpha=128)
  split = blender.load_split(str(tmp_path), "train", downscale=2)
  a = 128 / 255
  np.testing.assert_allclose(split.images[0, 0, 0], [1.0, 1.0 - a, 1.0 - a], rtol=1e-6)
  assert split.images.shape == (2, 4, 4, 3)
  assert split.intrinsics.width == 4 and split.intrinsics.fx == pytest.approx(2.0 / np.tan(0.345))


@pytest.mark.parametrize("corrupt,message", [
    ("missing_folder", "not found; set --config.data.path"),
    ("malformed_json", "is not valid JSON"),
    ("missing_keys", "needs the keys 'camera_angle_x'"),
    ("missing_image", "image file .*r_1.png not found"),
    ("wrong_size", "r_1.png is 6x6 pixels, but the split's first frame is 8x8"),
    ("nan_pose", "frame './train/r_1' contains NaN"),
])
def test_blender_bad_input_gets_one_clear_sentence(tmp_path, corrupt, message):
  root = tmp_path / "scene"
  meta = _write_scene(root, sizes={1: 6} if corrupt == "wrong_size" else None)
  if corrupt == "missing_folder":
    root = tmp_path / "nowhere"
  elif corrupt == "malformed_json":
    (root / "transforms_train.json").write_text('{"camera_angle_x": 0.69, "frames": [')
  elif corrupt == "missing_keys":
    (root / "transforms_train.json").write_text('{"frames": []}')
  elif corrupt == "missing_image":
    (root / "train" / "r_1.png").unlink()
  elif corrupt == "nan_pose":
    meta["frames"][1]["transform_matrix"][0][3] = float("nan")
    (root / "transforms_train.json").write_text(json.dumps(meta))
  with pytest.raises(UserError, match=message):
    blender.read(str(root))


def test_dispatch_refuses_unknown_kinds_and_missing_paths():
  cfg = ml_collections.ConfigDict({"kind": "nope", "path": "", "downscale": 1, "image_size": 8,
                                   "pixel_center": 0.5})
  with pytest.raises(UserError, match="unknown data.kind 'nope'"):  # the kind is named, not the missing path
    scenes.load(cfg)
  cfg.kind, cfg.path = "tiny", ""
  with pytest.raises(UserError, match="needs a data path"):
    scenes.load(cfg)
  cfg.path = "/nonexistent/tiny.npz"
  with pytest.raises(UserError, match="not found"):
    scenes.load(cfg)


def test_split_keeps_frames_of_any_size_as_uint8_and_gives_them_back_as_float():
  from nerfpod.nerf.cameras import Cameras, Intrinsics
  from nerfpod.scenes.base import Split, to_float, to_uint8
  levels = np.arange(256, dtype=np.uint8)
  np.testing.assert_array_equal(to_uint8(to_float(levels)), levels)  # exact on the 256 levels
  rng = np.random.default_rng(0)
  images = [rng.random((3, 4, 3)).astype(np.float32), rng.random((2, 5, 3)).astype(np.float32)]
  cams = Cameras.stack([Intrinsics.from_focal(4, 3, 5.0), Intrinsics.from_focal(5, 2, 6.0)])
  split = Split.from_images(images, np.tile(np.eye(4), (2, 1, 1)), cams, ["a", "b"])
  assert split.pixels.dtype == np.uint8 and split.pixels.shape == (22, 3)
  np.testing.assert_array_equal(split.offsets, [0, 12, 22])
  for i in (0, 1):
    np.testing.assert_allclose(split.image(i), images[i], atol=0.5 / 255 + 1e-7)
  only_b = split.select([1])
  assert only_b.names == ("b",) and only_b.cameras[0] == cams[1]
  np.testing.assert_array_equal(only_b.image_uint8(0), split.image_uint8(1))
  np.testing.assert_array_equal(split.images[1], split.image(1))  # one frame, converted when read
  assert split.images.size == 66 and len(split.images) == 2
  with pytest.raises(ValueError, match="differ in size"):
    np.asarray(split.images)
  with pytest.raises(UserError, match="frame b is 5x2 pixels but its camera is 4x3"):
    Split.from_images(images, np.tile(np.eye(4), (2, 1, 1)), Intrinsics.from_focal(4, 3, 5.0), ["a", "b"])


def test_every_loader_has_the_one_signature_and_a_new_format_is_one_table_entry(monkeypatch, tmp_path):
  import importlib
  import inspect
  import sys
  import types
  for kind, loader in scenes.LOADERS.items():
    parameters = list(inspect.signature(importlib.import_module(f"nerfpod.scenes.{loader.module}").load).parameters)
    assert len(parameters) == 3 and parameters[1:] == ["data_config", "shards"], (kind, parameters)
  assert scenes.KINDS == tuple(scenes.LOADERS) + ("auto",)
  assert scenes.CAPTURE_KINDS == ("llff", "colmap", "nerfstudio")
  assert scenes.HAS_ALPHA == {"procedural": True, "street": True, "tiny": False, "blender": True, "llff": False,
                              "colmap": False, "nerfstudio": False}
  # A format nerfpod has never seen: its module and one LOADERS entry, and scenes.load reads it.
  made = procedural.make(image_size=8, num_train=3, num_val=1, num_test=1)
  fake = types.ModuleType("nerfpod.scenes.pretend")
  calls = []
  fake.load = lambda path, data_config, shards=None: calls.append((path, data_config.downscale, shards)) or made
  monkeypatch.setitem(sys.modules, "nerfpod.scenes.pretend", fake)
  monkeypatch.setitem(scenes.LOADERS, "pretend", scenes.Loader("pretend"))
  data = ml_collections.ConfigDict({"kind": "pretend", "path": str(tmp_path), "downscale": 2})
  assert scenes.load(data) is made and calls == [(str(tmp_path), 2, None)]
  with pytest.raises(UserError, match=r"data.kind='pretend' needs a data path"):
    scenes.load(ml_collections.ConfigDict({"kind": "pretend", "path": "", "downscale": 1}))


@pytest.mark.parametrize("kind, path", [("procedural", ""), ("street", "blocks=2")])
def test_a_built_in_scenes_cameras_come_without_tracing_its_frames(kind, path):
  """scenes.cameras_only (what nerfpod aot measures model.region_capacity=auto on): the poses, cameras and
  bounds load() gives, every pixel the background and no coverage; a scene read from files is not for it."""
  data = ml_collections.ConfigDict({"kind": kind, "path": path, "image_size": 6, "pixel_center": 0.5})
  loaded, bare = scenes.load(data), scenes.cameras_only(data)
  assert (bare.name, bare.near, bare.far, bare.kind) == (loaded.name, loaded.near, loaded.far, loaded.kind)
  for name, split in loaded.splits.items():
    np.testing.assert_array_equal(bare.splits[name].poses, split.poses)
    for field in ("width", "height", "fx", "fy", "cx", "cy", "distortion"):
      np.testing.assert_array_equal(getattr(bare.splits[name].cameras, field), getattr(split.cameras, field))
    assert (np.asarray(bare.splits[name].pixels) == 255).all() and not np.asarray(bare.splits[name].alphas).any()
    assert np.asarray(split.alphas).any()  # (the traced frames do hit something)
  with pytest.raises(ValueError, match="data.kind=blender is not a built-in scene"):
    scenes.cameras_only(ml_collections.ConfigDict({"kind": "blender", "path": "/x"}))
