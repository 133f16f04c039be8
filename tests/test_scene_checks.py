"""What every scene loader checks, whatever the format: poses are rigid camera-to-world transforms; data.kind=auto
says what it skipped; a missing or empty image folder is named; images are read once, into their final
buffer. Small synthetic scenes (8x8 images) in each format, written by tests/test_captures.py's writers."""
import json
import logging
import os
import tracemalloc

import numpy as np
import pytest
from PIL import Image

from conftest import DATA, LEGO, TINY_NPZ, require
from nerfpod import scenes
from nerfpod.errors import UserError
from nerfpod.nerf import cameras
from nerfpod.scenes import base, capture
from test_captures import as_is, write_colmap_bin, write_images, write_llff, write_transforms

SIZE = 8


def _poses(n):
  return np.stack([cameras.spherical_pose(360.0 * i / n, -30.0, 4.0) for i in range(n)])


def _images(n, size=SIZE):
  rng = np.random.default_rng(0)
  return [rng.integers(0, 256, (size, size, 3), dtype=np.uint8) for _ in range(n)]


def _names(n):
  return [f"{i:02d}.png" for i in range(n)]


def _write(kind, root, poses, images=None):
  """A scene of `poses` in format `kind` under root; returns data.path."""
  n = len(poses)
  images = _images(n) if images is None else images
  names = _names(n)
  if kind == "blender":
    write_images(root / "train", names, images)
    frames = [{"file_path": f"./train/{os.path.splitext(m)[0]}", "transform_matrix": p.tolist()}
              for m, p in zip(names, poses)]
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.69, "frames": frames}))
  elif kind == "nerfstudio":
    write_transforms(root, poses, SIZE, SIZE, 10.0, 10.0, SIZE / 2, SIZE / 2, names)
    write_images(root / "images", names, images)
  elif kind == "llff":
    write_llff(root, poses, 10.0, images, names)
  elif kind == "colmap":
    write_colmap_bin(root / "sparse" / "0", poses, [(SIZE, SIZE, (10.0, 10.0, SIZE / 2, SIZE / 2), m) for m in names])
    write_images(root / "images", names, images)
  elif kind == "tiny":
    path = root / "tiny.npz"
    frames = np.zeros((101, SIZE, SIZE, 3), np.float32)
    np.savez(path, images=frames, poses=np.concatenate([poses, np.tile(poses[:1], (101 - n, 1, 1))]), focal=10.0)
    return path
  return root


# --- 5. Poses are rigid transforms. ---

def _scaled(p):
  p[:3, :3] *= 1.5
  return p


def _sheared(p):
  p[:3, 0] += 0.1 * p[:3, 1]
  return p


def _mirrored(p):
  p[:3, 0] *= -1
  return p


def _last_row(p):
  p[3] = [0.0, 0.0, 0.5, 1.0]
  return p


def _zero(p):
  p[:] = 0.0
  return p


BAD_POSES = {"all zeros": (_zero, "all-zero rotation"), "scaled": (_scaled, "rotation scaled by 1.5"),
             "sheared": (_sheared, "not orthonormal"), "mirrored": (_mirrored, "mirrored rotation"),
             "last row": (_last_row, "the last row 0 0 0.5 1 instead of 0 0 0 1")}
# Where the format stores the pose: what the message calls it, and which bad poses it can hold at all (LLFF
# has no last row; its hwf column leaves only the rotation and translation).
FORMATS = {"blender": ("transform_matrix", "transforms_train.json", "./train/02"),
           "nerfstudio": ("transform_matrix", "transforms.json", "images/02.png"),
           "llff": ("pose", "poses_bounds.npy", "images/02.png"),
           "tiny": ("pose", "tiny.npz", "2")}


@pytest.mark.parametrize("kind", sorted(FORMATS))
@pytest.mark.parametrize("bad", sorted(BAD_POSES))
def test_every_loader_refuses_a_pose_that_is_not_rigid_naming_the_frame_and_the_file(tmp_path, kind, bad):
  if kind == "llff" and bad == "last row":
    pytest.skip("poses_bounds.npy stores 3x4 poses: there is no last row to be wrong")
  if kind in SCALE_TAKEN and bad == "scaled":
    pytest.skip("a uniformly scaled transform_matrix is taken, its axes as unit vectors (test below)")
  change, expected = BAD_POSES[bad]
  poses = _poses(4)
  poses[2] = change(poses[2].copy())
  path = _write(kind, tmp_path, poses)
  what, file, frame = FORMATS[kind]
  with pytest.raises(UserError) as err:
    scenes.load(as_is(kind, path))
  message = str(err.value)
  assert f"{tmp_path / file}: the {what} of frame {frame!r} is not a rigid camera-to-world transform" in message
  assert expected in message and message.endswith("; fix or remove that frame.")
  assert "\n" not in message and message.rstrip(".").count(". ") == 0


SCALE_TAKEN = ("blender", "nerfstudio")  # the formats whose transform_matrix some tools write with a scale


@pytest.mark.parametrize("kind", SCALE_TAKEN)
def test_a_uniformly_scaled_transform_matrix_loads_as_its_unit_axes_with_a_note(tmp_path, kind, capsys):
  poses = _poses(4)
  scaled = poses.copy()
  scaled[2, :3, :3] *= 1.5
  (tmp_path / "unit").mkdir()
  (tmp_path / "scaled").mkdir()
  want = scenes.load(as_is(kind, _write(kind, tmp_path / "unit", poses)))
  capsys.readouterr()
  got = scenes.load(as_is(kind, _write(kind, tmp_path / "scaled", scaled)))
  note = capsys.readouterr().err
  assert "the transform_matrix of 1 frame(s) has its rotation scaled by 1.5..1.5; their axes are used as unit " \
         "vectors (positions unchanged)" in note, note
  for name in want.splits:
    np.testing.assert_allclose(got.split(name).poses, want.split(name).poses, atol=1e-6)


def test_colmap_poses_are_checked_too_and_every_bad_frame_is_counted():
  """COLMAP stores unit quaternions (always a rotation): its loader runs the same check on the world-to-camera
  poses it reads; the check counts the other bad frames."""
  poses = _poses(5)
  base.check_poses(poses, _names(5), "here")
  poses[1, :3, :3] = 0.0
  poses[3, :3, :3] *= 2.0
  with pytest.raises(UserError, match=r"^here: the pose of frame '01.png' \(and 1 more frame\) is not a rigid"):
    base.check_poses(poses, _names(5), "here")
  poses[4, 0, 0] = np.nan
  with pytest.raises(UserError, match=r"frame '04.png' contains NaN or infinity"):  # NaN is said first
    base.check_poses(poses, _names(5), "here")


def test_the_real_captures_are_rigid_well_within_the_tolerance():
  """The tolerance (base.RIGID_TOLERANCE, 1e-3) against the shared real captures: every pose is within 1e-5
  of a rotation (they are float32 round-off, 1.3e-6 at most), so they load with two orders of margin."""
  from nerfpod.scenes import llff
  require(DATA)
  found = []
  for path in (LEGO / "transforms_train.json", DATA / "nerfstudio_fox" / "transforms.json"):
    require(path)
    frames = json.loads(path.read_text())["frames"]
    found.append(np.array([f["transform_matrix"] for f in frames], np.float64))
  for path in (DATA / "llff_horns" / "poses_bounds.npy", DATA / "colmap_cup" / "poses_bounds.npy"):
    require(path)
    found.append(llff.read_poses_bounds(str(path))[0])
  require(TINY_NPZ)
  with np.load(TINY_NPZ) as npz:
    found.append(npz["poses"].astype(np.float64))
  for poses in found:
    rotation = poses[:, :3, :3]
    off = np.abs(np.einsum("nki,nkj->nij", rotation, rotation) - np.eye(3)).max()
    assert off < base.RIGID_TOLERANCE / 100
    base.check_poses(poses, [str(i) for i in range(len(poses))], "real")


# --- 6. data.kind=auto and an incomplete COLMAP model. ---

def _broken_colmap(root, with_llff):
  poses = _poses(3)
  _write("colmap", root, poses)
  os.remove(root / "sparse" / "0" / "images.bin")
  if with_llff:
    write_llff(root, poses, 10.0, _images(3), _names(3))


def test_auto_skips_an_incomplete_colmap_model_saying_which_file_it_lacks(tmp_path):
  _broken_colmap(tmp_path, with_llff=True)
  missing = tmp_path / "sparse" / "0" / "images.bin"
  # Read off absl's logger itself, at WARNING whatever an earlier test in this process set it to.
  records = []
  handler = logging.Handler(logging.WARNING)
  handler.emit = records.append
  absl_logger = logging.getLogger("absl")
  level = absl_logger.level
  absl_logger.addHandler(handler)
  absl_logger.setLevel(logging.WARNING)
  try:
    assert scenes.detect(str(tmp_path)) == "llff"
  finally:
    absl_logger.removeHandler(handler)
    absl_logger.setLevel(level)
  warning = " ".join(r.getMessage() for r in records if r.levelno == logging.WARNING)
  assert f"found a COLMAP model in {tmp_path / 'sparse' / '0'} but {missing} is missing" in warning
  assert "using poses_bounds.npy (llff) instead" in warning
  with pytest.raises(UserError) as err:  # data.kind=colmap insists, and names the file
    scenes.load(as_is("colmap", tmp_path))
  assert str(err.value) == (f"the COLMAP model in {tmp_path / 'sparse' / '0'} is incomplete: {missing} is missing; "
                            f"restore it or re-export the model from COLMAP (cameras, images and points3D, as "
                            f".bin or .txt).")


def test_auto_refuses_an_incomplete_colmap_model_with_nothing_beside_it(tmp_path):
  _broken_colmap(tmp_path, with_llff=False)
  os.remove(tmp_path / "sparse" / "0" / "points3D.bin")
  with pytest.raises(UserError, match=(f"holds an incomplete COLMAP model and no other scene: in "
                                       f"{tmp_path / 'sparse' / '0'}, {tmp_path / 'sparse' / '0' / 'images.bin'}, "
                                       f"{tmp_path / 'sparse' / '0' / 'points3D.bin'} are missing; restore them")):
    scenes.detect(str(tmp_path))


# --- 7. An empty images_N/ folder is named. ---

@pytest.mark.parametrize("kind", ["llff", "colmap"])
def test_an_empty_images_n_folder_is_named_with_the_ways_out(tmp_path, kind):
  if kind == "colmap":
    pytest.importorskip("pycolmap")
  _write(kind, tmp_path, _poses(3), _images(3, size=4 * SIZE) if kind == "llff" else None)
  (tmp_path / "images_4").mkdir()
  with pytest.raises(UserError) as err:
    scenes.load(as_is(kind, tmp_path, downscale=4))
  message = str(err.value)
  assert f"{tmp_path / 'images_4'}/, but that folder holds no images; regenerate images_4/ as the images of " \
         f"images/ shrunk 4 times, delete the empty images_4/ to have images/ shrunk on loading, or use " \
         f"--config.data.downscale=1." in message, message
  if kind == "colmap":
    assert message.startswith("the COLMAP model in ") and "lists 3 images (00.png, 01.png, 02.png)" in message
  os.rmdir(tmp_path / "images_4")  # the second way out: images/ shrunk on loading
  assert scenes.load(as_is(kind, tmp_path, downscale=4 if kind == "llff" else 1)).split("train").pixels.size


def test_images_missing_from_a_folder_that_has_others_are_named_with_the_folder(tmp_path):
  _write("nerfstudio", tmp_path, _poses(3))
  os.remove(tmp_path / "images" / "01.png")
  with pytest.raises(UserError, match=(f"lists 1 image\\(s\\) of its 3 frames that do not exist in "
                                       f"{tmp_path / 'images'}/ \\(images/01.png\\)")):
    scenes.load(as_is("nerfstudio", tmp_path))


# --- 8. Images are read once, into their split's buffer. ---

def test_loading_holds_the_frames_once_plus_the_images_in_flight(tmp_path, monkeypatch):
  """The peak of traced allocations (numpy's buffers and Python's objects, tracemalloc) while loading 32
  frames is their final pixel buffers plus a few images per reading thread and a fixed allowance for the
  loader's own objects, where a list of decoded images concatenated into the buffer (the loaders before)
  peaked at three times the buffers."""
  n, w, h = 32, 160, 120
  rng = np.random.default_rng(0)
  write_transforms(tmp_path, _poses(n), w, h, 100.0, 100.0, w / 2, h / 2, _names(n))
  write_images(tmp_path / "images", _names(n), [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(n)])
  monkeypatch.setattr(capture, "READ_THREADS", 2)  # the same bound on any machine
  config = as_is("nerfstudio", tmp_path)
  scenes.load(config)  # imports and first-use caches outside the measurement
  tracemalloc.start()
  try:
    scene = scenes.load(config)
    peak = tracemalloc.get_traced_memory()[1]
  finally:
    tracemalloc.stop()
  buffers = sum(s.pixels.nbytes for s in {id(s): s for s in scene.splits.values()}.values())
  assert buffers == n * w * h * 3
  one_image = w * h * 3
  assert buffers <= peak < buffers + 2 * 3 * one_image + 512 * 1024, (peak, buffers)


def test_split_from_frames_reads_each_frame_into_its_slot_and_names_a_bad_one():
  from nerfpod.nerf.cameras import Cameras, Intrinsics
  cams = Cameras.stack([Intrinsics.from_focal(4, 3, 5.0), Intrinsics.from_focal(5, 2, 6.0)])
  images = _images(2, 5)
  rgb = [images[0][:3, :4], images[1][:2, :5]]
  split = base.Split.from_frames(lambda i: (rgb[i], rgb[i][..., 0]), np.tile(np.eye(4), (2, 1, 1)), cams,
                                 ["a", "b"], with_alpha=True, threads=2)
  for i in (0, 1):
    np.testing.assert_array_equal(split.image_uint8(i), rgb[i])
    np.testing.assert_array_equal(split.alpha(i), rgb[i][..., 0] / np.float32(255))
  with pytest.raises(UserError, match="the image of frame b is 4x3 pixels but its camera is 5x2"):
    base.Split.from_frames(lambda i: (rgb[0], None), np.tile(np.eye(4), (2, 1, 1)), cams, ["a", "b"], threads=2)


@pytest.mark.parametrize("kind", ["blender", "nerfstudio", "colmap", "llff"])
@pytest.mark.parametrize("damage", ["truncated", "not an image"])
def test_a_damaged_image_is_one_sentence_naming_its_file(tmp_path, kind, damage):
  """An image cut off (a copy that stopped) or not an image at all (a text file under an image's name): one
  sentence naming the file, whichever loader reads it."""
  path = _write(kind, tmp_path, _poses(6))
  bad = sorted(p for p in tmp_path.rglob("03.png"))[0]
  data = bad.read_bytes()
  bad.write_bytes(data[:len(data) // 2] if damage == "truncated" else b"<html>404</html>")
  with pytest.raises(UserError) as refused:
    scenes.load(as_is(kind, path)).split("train").image(3)
  message = str(refused.value)
  reason = "image file is truncated" if damage == "truncated" else "not an image format it reads"
  assert message.endswith(f"03.png is not a readable image ({reason}); copy it again, or remove the frame."), message
  assert "\n" not in message and "BufferedReader" not in message


def test_a_damaged_training_image_exits_2_with_one_sentence_and_no_workdir(tmp_path, capsys, monkeypatch,
                                                                            run_start_held):
  """Through the command line (nerfpod.main.run, in this process: refused by the run's start-up, which
  conftest.run_start_held undoes): the sentence, exit 2, and no workdir made."""
  import procs
  from conftest import REPO
  from nerfpod import main
  (tmp_path / "capture").mkdir()
  path = _write("nerfstudio", tmp_path / "capture", _poses(6))
  bad = path / "images" / "03.png"
  bad.write_bytes(bad.read_bytes()[:40])
  result = procs.in_process(main.run, "nerfpod.main", capsys, monkeypatch, REPO)(
      "--config=configs/default.py:smoke", f"--workdir={tmp_path / 'run'}", "--config.data.kind=auto",
      f"--config.data.path={path}")
  assert result.returncode == 2, result.stderr[-2000:]
  errors = [line for line in result.stderr.splitlines() if line.startswith("nerfpod: error:")]
  assert len(errors) == 1 and f"{bad} is not a readable image" in errors[0], result.stderr[-2000:]
  assert "Traceback" not in result.stderr and not (tmp_path / "run").exists()
