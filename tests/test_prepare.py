"""nerfpod prepare: the pure pieces (frame selection, camera and matching choice, the choice between the mappers'
models and its reruns, the LLFF and nerfstudio writers, the report), every bad input, and real runs of pycolmap's
SfM end to end: on a textured scene rendered here with known cameras (photos and a video with blurred frames; the
same capture twice, bit for bit; another seed; a disagreement between the mappers forced), on 20 of the shared
LLFF horns images, on the shared COLMAP cup (slow), and a video of the horns that configs/llff.py then trains on
(slow). Recovered poses are compared with the known ones after a similarity alignment (Umeyama)."""
import importlib.util
import json
import os
import re
import time

import numpy as np
import pytest
from PIL import Image, ImageFilter

from conftest import DATA, load_config, require
from nerfpod import prepare
from nerfpod.errors import UserError
from nerfpod.nerf.cameras import Intrinsics, image_rays, look_at
from nerfpod.prepare import capture, frames, progress, sfm

# Structure from motion needs pycolmap (the colmap extra); the pure pieces and the input checks do not.
needs_pycolmap = pytest.mark.skipif(importlib.util.find_spec("pycolmap") is None,
                                    reason="pycolmap (pip install 'nerfpod[colmap]') is not installed")


# --------------------------------------------------------------------------------------------------------------
# Helpers: a textured scene with known cameras, pose comparison


def _texture(u, v, seed):
  """Random colour cells at two scales over [-1, 1]^2: corners and blobs for SIFT."""
  rng = np.random.default_rng(seed)
  out = 0.0
  for cells, weight in ((6, 0.55), (23, 0.45)):
    table = rng.uniform(0, 1, (cells, cells, 3))
    x = np.clip((u * 0.5 + 0.5) * cells, 0, cells - 1e-6).astype(int)
    y = np.clip((v * 0.5 + 0.5) * cells, 0, cells - 1e-6).astype(int)
    out = out + weight * table[x, y]
  return out


def render_textured(c2w, width, height, focal) -> np.ndarray:
  """A textured 4x4 floor (z = 0) with a textured box on it, ray-traced: (H, W, 3) uint8."""
  o, d = image_rays(c2w, Intrinsics.from_focal(width, height, focal))
  colour, best = np.full(o.shape, 0.8), np.full(o.shape[:-1], np.inf)
  with np.errstate(divide="ignore", invalid="ignore"):
    t = -o[..., 2] / d[..., 2]
  p = o + t[..., None] * d
  hit = (t > 0) & (np.abs(p[..., 0]) < 2) & (np.abs(p[..., 1]) < 2)
  best = np.where(hit, t, best)
  colour = np.where(hit[..., None], _texture(p[..., 0] / 2, p[..., 1] / 2, 1), colour)
  lo, hi = np.array([-0.5, -0.3, 0.0]), np.array([0.5, 0.3, 0.8])
  with np.errstate(divide="ignore", invalid="ignore"):
    t0, t1 = (lo - o) / d, (hi - o) / d
  t_near, t_far = np.minimum(t0, t1).max(-1), np.maximum(t0, t1).min(-1)
  hit = (t_near <= t_far) & (t_near > 0) & (t_near < best)
  q = (o + t_near[..., None] * d - (lo + hi) / 2) / ((hi - lo) / 2)
  axis = np.argmax(np.minimum(t0, t1), -1)
  faces = [(q[..., 1], q[..., 2]), (q[..., 0], q[..., 2]), (q[..., 0], q[..., 1])]
  tex = np.zeros_like(colour)
  for a, (u, v) in enumerate(faces):
    tex = np.where((axis == a)[..., None], _texture(u, v, 10 + a), tex)
  colour = np.where(hit[..., None], tex, colour)
  return (np.clip(colour, 0, 1) * 255).round().astype(np.uint8)


def ring_poses(n: int) -> np.ndarray:
  """n OpenGL camera-to-world poses around the box, in azimuth order, at elevations 30 and 45 degrees."""
  az = np.linspace(0, 2 * np.pi, n, endpoint=False)
  el = np.deg2rad(np.where(np.arange(n) % 2, 30.0, 45.0))
  eyes = 3.5 * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
  return np.stack([look_at(e, target=(0.0, 0.0, 0.3)) for e in eyes])


def umeyama(src_Nx3, dst_Nx3):
  """The similarity (s, R, t) minimising |s R src + t - dst|^2 (Umeyama 1991)."""
  ms, md = src_Nx3.mean(0), dst_Nx3.mean(0)
  x, y = src_Nx3 - ms, dst_Nx3 - md
  u, sv, vt = np.linalg.svd(y.T @ x / len(x))
  d = np.eye(3)
  d[2, 2] = np.sign(np.linalg.det(u @ vt))
  r = u @ d @ vt
  s = np.trace(np.diag(sv) @ d) / (x**2).sum(1).mean()
  return s, r, md - s * r @ ms


def pose_errors(estimated: dict, known: dict) -> tuple[np.ndarray, np.ndarray]:
  """Per common frame: rotation error (degrees) and camera-centre error (as a share of the known cameras' mean
  distance from their centroid). The centres are compared after the similarity that best aligns the estimated
  centres to the known ones; the orientations after the rotation that best aligns the estimated orientations to
  the known ones (the chordal mean of known @ estimated^T). The centres alone fix the frame's rotation poorly
  where the cameras lie near a plane or a line (a forward-facing capture): on 20 horns photos 1.5% of centre
  noise turned every camera by 0.9-1.0 degrees through that rotation, while their orientations agree within
  0.2-0.4 degrees."""
  names = sorted(set(estimated) & set(known))
  a = np.array([estimated[n][:3, 3] for n in names])
  b = np.array([known[n][:3, 3] for n in names])
  s, r, t = umeyama(a, b)
  position = np.linalg.norm((s * (r @ a.T)).T + t - b, axis=1) / np.linalg.norm(b - b.mean(0), axis=1).mean()
  u, _, vt = np.linalg.svd(sum(known[n][:3, :3] @ estimated[n][:3, :3].T for n in names))
  r = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
  cosines = [(np.trace((r @ estimated[n][:3, :3]).T @ known[n][:3, :3]) - 1) / 2 for n in names]
  return np.degrees(np.arccos(np.clip(cosines, -1, 1))), position


def scene_poses(scene) -> dict:
  """{image file name: OpenGL camera-to-world} over every split of a loaded Scene."""
  return {os.path.basename(name): pose for split in scene.splits.values()
          for name, pose in zip(split.names, split.poses)}


def capture_config(path, downscale=1):
  """configs/capture.py's config for the capture at `path`."""
  return load_config("capture", f"path={path},downscale={downscale}")


def run_prepare(capsys, *args) -> tuple[int, str, str]:
  """`nerfpod prepare ARGS` in this process: (exit code, stdout, stderr)."""
  try:
    code = prepare.run([str(a) for a in args])
  except SystemExit as e:
    code = e.code
  out, err = capsys.readouterr()
  return code, out, err


def write_photos(folder, poses, width=160, height=120, focal=144.0):
  os.makedirs(folder, exist_ok=True)
  for i, c2w in enumerate(poses):
    Image.fromarray(render_textured(c2w, width, height, focal)).save(os.path.join(folder, f"view_{i:03d}.png"))
  return folder


def write_video(path, video_frames, fps=10):
  import imageio_ffmpeg
  h, w = video_frames[0].shape[:2]
  writer = imageio_ffmpeg.write_frames(str(path), (w, h), fps=fps, quality=9, macro_block_size=8)
  writer.send(None)
  for frame in video_frames:
    writer.send(np.ascontiguousarray(frame))
  writer.close()


# --------------------------------------------------------------------------------------------------------------
# Pure pieces


def test_sharpness_ranks_a_blurred_copy_below_the_original():
  rng = np.random.default_rng(0)
  sharp = np.kron(rng.integers(0, 255, (30, 40, 3)), np.ones((4, 4, 1))).astype(np.uint8)
  blurred = np.asarray(Image.fromarray(sharp).filter(ImageFilter.GaussianBlur(2)))
  assert frames.sharpness(sharp) > 2 * frames.sharpness(blurred) > 0
  big = np.kron(sharp, np.ones((20, 20, 1), np.uint8))  # 2400 wide: subsampled, still ranked
  assert frames.sharpness(big) > frames.sharpness(np.kron(blurred, np.ones((20, 20, 1), np.uint8)))


def test_frame_windows_cover_the_video_evenly():
  edges = frames.frame_windows(100, 10)
  assert edges[0] == 0 and edges[-1] == 100 and len(edges) == 11 and set(np.diff(edges)) == {10}
  assert len(frames.frame_windows(7, 150)) == 8  # fewer frames than asked: every frame
  assert frames.window_of(0, edges) == 0 and frames.window_of(99, edges) == 9
  assert frames.window_of(130, edges) == 9  # a video with more frames than it said: the last window


def test_pick_sharpest_takes_the_sharp_frame_of_each_window():
  scores = np.tile([1.0, 5.0, 2.0], 8)  # blurred, sharp, blurred
  assert frames.pick_sharpest(scores, 8) == [3 * k + 1 for k in range(8)]
  assert frames.pick_sharpest(np.arange(10.0), 3) == [2, 6, 9]


def test_cameras_are_shared_for_one_camera_else_one_per_image():
  same = [(640, 480)] * 5
  assert sfm.choose_cameras("video", same, [None]) == "shared"
  assert sfm.choose_cameras("photos", same, [("Apple", "iPhone 13")] * 5) == "shared"
  assert sfm.choose_cameras("photos", same, [None] * 5) == "shared"
  assert sfm.choose_cameras("photos", same, [("Apple", "iPhone 13")] * 4 + [("Google", "Pixel 7")]) == \
      "per_image"
  mixed = same[:4] + [(480, 640)]
  assert sfm.choose_cameras("photos", mixed, [None] * 5) == "per_image"
  assert sfm.choose_cameras("photos", same, [None] * 5, "per_image") == "per_image"
  with pytest.raises(UserError, match=r"--cameras=shared needs images of one size.*2 sizes"):
    sfm.choose_cameras("photos", mixed, [None] * 5, "shared")
  assert sfm.choose_camera_model() == "SIMPLE_RADIAL"
  assert sfm.choose_camera_model("OPENCV") == "OPENCV"


def test_matching_is_sequential_for_video_and_many_photos():
  assert sfm.choose_matching("video", 150) == "sequential"
  assert sfm.choose_matching("photos", 80) == "exhaustive"
  assert sfm.choose_matching("photos", sfm.EXHAUSTIVE_MAX_IMAGES + 1) == "sequential"
  assert sfm.choose_matching("video", 150, "exhaustive") == "exhaustive"


def test_image_pairs():
  assert sfm.image_pairs(5, "exhaustive") == [(i, j) for i in range(5) for j in range(i + 1, 5)]
  pairs = sfm.image_pairs(150, "sequential")
  assert len(pairs) == len(set(pairs)) and all(i < j < 150 for i, j in pairs)
  assert all((i, i + d) in pairs for i in range(140) for d in range(1, 11))  # neighbours in time
  assert (0, 64) in pairs and (10, 138) in pairs  # quadratic overlap: i + 2^k
  assert (0, 149) in pairs  # loop pairs among 20 evenly spaced frames close the circle
  assert len(pairs) < 150 * 149 // 2 // 4


def test_downscale_folders_only_for_large_images():
  assert capture.downscale_factors(4032, 3024) == [2, 4, 8]
  assert capture.downscale_factors(800, 600) == [2, 4]
  assert capture.downscale_factors(252, 189) == []


def test_safe_names_replace_whitespace_uniquely():
  names = frames.safe_names(["a b.jpg", "a_b.jpg", "c.png"])
  assert names["c.png"] == "c.png" and len(set(names.values())) == 3
  assert not any(" " in n for n in names.values())


def _model(n=6, shared=True, seed=0):
  rng = np.random.default_rng(seed)
  poses = ring_poses(n) @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenGL -> OpenCV camera axes
  poses[:, :3, 3] += rng.normal(0, 0.1, (n, 3))
  w2c = np.linalg.inv(poses)[:, :3, :]
  cameras = {1: {"model": "SIMPLE_RADIAL", "width": 200, "height": 150, "params": [180.0, 100.0, 75.0, 0.02]}}
  ids = [1] * n
  if not shared:
    cameras[2] = {"model": "OPENCV", "width": 150, "height": 200,
                  "params": [170.0, 171.0, 75.0, 100.0, 0.01, -0.02, 0.001, 0.002]}
    ids = [1, 2] * (n // 2)
  bounds = np.stack([rng.uniform(1, 2, n), rng.uniform(5, 9, n)], 1)
  return capture.Model([f"{i:02d}.jpg" for i in range(n)], w2c, ids, cameras, bounds)


def test_poses_bounds_reads_back_through_the_llff_loader(tmp_path):
  from nerfpod.scenes import llff
  model = _model(shared=False)
  np.save(tmp_path / "poses_bounds.npy", capture.poses_bounds(model))
  poses, hwf, bounds = llff.read_poses_bounds(str(tmp_path / "poses_bounds.npy"))
  np.testing.assert_allclose(poses, model.c2w_opencv() @ capture.OPENCV_TO_OPENGL, atol=1e-9)
  np.testing.assert_allclose(hwf[0], [150, 200, 180.0]) and np.testing.assert_allclose(hwf[1], [200, 150, 170.0])
  np.testing.assert_allclose(bounds, model.bounds)


def test_transforms_json_shared_and_per_image_cameras():
  shared = capture.transforms_json(_model())
  assert shared["camera_model"] == "OPENCV" and shared["fl_x"] == shared["fl_y"] == 180.0
  assert shared["k1"] == 0.02 and shared["w"] == 200 and shared["frames"][0]["file_path"] == "images/00.jpg"
  assert "fl_x" not in shared["frames"][0]
  c2w = np.array(shared["frames"][3]["transform_matrix"])
  np.testing.assert_allclose(c2w, _model().c2w_opencv()[3] @ capture.OPENCV_TO_OPENGL)
  per_image = capture.transforms_json(_model(shared=False))
  assert "fl_x" not in per_image and per_image["frames"][1]["fl_y"] == 171.0
  assert per_image["frames"][1]["p2"] == 0.002 and per_image["frames"][0]["k1"] == 0.02


def test_forward_facing():
  assert not capture.looks_forward_facing(_model(12).c2w_opencv())
  forward = np.tile(np.eye(4), (5, 1, 1))
  forward[:, 0, 3] = np.arange(5)
  assert capture.looks_forward_facing(forward)


def _moved(poses: dict, scale=2.0, angle=0.7, shift=(1.0, -2.0, 0.5)) -> dict:
  """The same cameras in another frame: a similarity applied to every camera-to-world pose."""
  c, s_ = np.cos(angle), np.sin(angle)
  m = np.eye(4)
  m[:3, :3] = scale * np.array([[c, -s_, 0], [s_, c, 0], [0, 0, 1]])
  m[:3, 3] = shift
  out = {}
  for k, p in poses.items():
    q = m @ p
    q[:3, :3] /= scale
    out[k] = q
  return out


def test_pose_agreement_is_blind_to_a_similarity_and_matches_umeyama():
  poses = {f"{i}": p for i, p in enumerate(_model(12).c2w_opencv())}
  same = sfm.pose_agreement(_moved(poses), poses)
  assert same["common"] == 12 and same["rotation_deg"] < 1e-4 and same["centre"] < 1e-9
  rotation, centre = pose_errors(_moved(poses), poses)  # the tests' own Umeyama
  assert np.median(rotation) < 1e-4 and np.median(centre) < 1e-9
  bent = dict(poses)
  for k in list(bent)[:7]:  # most cameras turned by 20 degrees about their own x axis
    r = np.eye(4)
    r[1:3, 1:3] = [[np.cos(0.35), -np.sin(0.35)], [np.sin(0.35), np.cos(0.35)]]
    bent[k] = bent[k] @ r
  far = sfm.pose_agreement(bent, poses)
  # (20.05 degrees after the centres' rotation, which is the identity here: the joint fit of centres and
  # orientations takes a part of the seven cameras' turn into the frame's rotation)
  assert 12.0 < far["rotation_deg"] < 20.05 and not sfm.agrees(far)


def _angle_deg(r):
  return np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0)))


def test_pose_agreement_of_a_straight_walk_is_not_turned_by_noise_in_its_centres():
  """Cameras along a line (a walk down a street, looking to the side and turning a little): the line leaves a
  rotation about itself free, which the centres alone fix from their noise; the orientations fix it."""
  rng = np.random.default_rng(0)
  poses = {}
  for i in range(20):
    yaw = 0.3 * np.sin(i / 3.0)  # the walker's head turning
    c, s_ = np.cos(yaw), np.sin(yaw)
    p = np.eye(4)
    p[:3, :3] = np.array([[c, 0, s_], [0, 1, 0], [-s_, 0, c]]) @ np.diag([1.0, -1.0, -1.0])
    p[:3, 3] = (0.25 * i, 0.0, 0.0) + rng.normal(scale=0.01, size=3)  # one mapper's estimate
    poses[f"{i}"] = p
  other = _moved(poses)
  for k, p in other.items():  # another mapper's estimate: centres off by about 3% of the cameras' spread, turns of 0.1 degrees
    p[:3, 3] += rng.normal(scale=0.005 * 4.75 * 2.0, size=3)
    axis = rng.normal(size=3)
    angle = np.radians(0.1) * axis / np.linalg.norm(axis)
    k_ = np.array([[0, -angle[2], angle[1]], [angle[2], 0, -angle[0]], [-angle[1], angle[0], 0]])
    p[:3, :3] = p[:3, :3] @ (np.eye(3) + k_ + k_ @ k_ / 2)
  agreement = sfm.pose_agreement(other, poses)
  assert agreement["rotation_deg"] < 0.3 and agreement["centre"] < 0.05 and sfm.agrees(agreement)
  # The centres' rotation alone turns this frame by degrees about the line (what the agreement measured before).
  names = sorted(poses)
  _, r, _ = sfm.similarity(np.array([other[n][:3, 3] for n in names]), np.array([poses[n][:3, 3] for n in names]))
  turned = np.median([_angle_deg((r @ other[n][:3, :3]).T @ poses[n][:3, :3]) for n in names])
  assert turned > 5.0, turned


def test_choosing_the_model_of_two_mappers():
  poses = {f"{i}": p for i, p in enumerate(_model(12).c2w_opencv())}
  incremental = {"mapper": "incremental", "registered": 10, "reprojection_error": 0.9,
                 "poses": {k: poses[k] for k in list(poses)[:10]}}
  good_global = {"mapper": "global", "registered": 12, "reprojection_error": 0.5, "poses": _moved(poses)}
  best, note, choice = sfm.choose_model([incremental, good_global])
  assert best is good_global and "agreed with it" in note and choice == {"reason": "agreed", "reruns": []}
  wrong = dict(good_global, poses={k: p @ np.diag([1.0, -1.0, -1.0, 1.0]) for k, p in poses.items()})
  best, note, choice = sfm.choose_model([dict(incremental), wrong])  # more images, but upside down: not trusted
  assert best["mapper"] == "incremental" and "disagreed" in note and choice["reason"] == "disagreed"
  few = dict(incremental, registered=3, poses={k: poses[k] for k in list(poses)[:3]})
  assert sfm.choose_model([few, wrong])[0] is wrong  # 3 images check nothing
  tie = dict(good_global, registered=10, reprojection_error=1.2)
  assert sfm.choose_model([incremental, tie])[0] is incremental  # a tie: the lower reprojection error
  assert sfm.choose_model([incremental]) == (incremental, "", {"reason": "one mapper", "reruns": []})


def _flipped(poses: dict) -> dict:
  """The cameras each turned upside down (180 degrees about their x axis): a model that disagrees."""
  return {k: p @ np.diag([1.0, -1.0, -1.0, 1.0]) for k, p in poses.items()}


def _candidates():
  """A global model of 12 cameras (right, in another frame), an incremental one of 10 of them turned upside down
  (wrong), with per-image figures, and the reruns a fake mapper gives by seed: 1 wrong with 11 images, 2 right
  with 11 images (each run a new dict, as run_mapper's)."""
  poses = {f"{i:02d}.jpg": p for i, p in enumerate(_model(12).c2w_opencv())}
  names = sorted(poses)

  def per_image(keep, error, track):
    return {k: {"observations": 100, "error_px": error, "track_length": track} for k in keep}

  glob = {"mapper": "global", "seed": 0, "registered": 12, "reprojection_error": 0.5, "poses": _moved(poses),
          "per_image": per_image(names, 0.5, 5.0), "models": 1, "others": 0, "seconds": 2.0}
  first = {"mapper": "incremental", "seed": 0, "registered": 10, "reprojection_error": 0.9,
           "poses": _flipped({k: poses[k] for k in names[:10]}), "per_image": per_image(names[:10], 0.9, 3.0),
           "models": 1, "others": 0, "seconds": 1.0}
  reruns = {1: dict(first, seed=1, registered=11, poses=_flipped({k: poses[k] for k in names[:11]}),
                    per_image=per_image(names[:11], 0.8, 3.5), rerun=True),
            2: dict(first, seed=2, registered=11, reprojection_error=0.7, poses={k: poses[k] for k in names[1:]},
                    per_image=per_image(names[1:], 0.7, 4.0), rerun=True)}
  return glob, first, reruns


def test_a_global_model_that_disagrees_is_kept_when_a_rerun_of_the_incremental_mapper_agrees():
  glob, first, reruns = _candidates()
  asked = []

  def rerun(k):
    asked.append(k)
    return dict(reruns[k])
  best, note, choice = sfm.choose_model([first, glob], rerun)
  assert asked == [1, 2] and best is glob and choice["reason"] == "agreed with a rerun"
  assert [r["seed"] for r in choice["reruns"]] == [1, 2]
  assert "disagreed with the incremental model on the 10 images both placed" in note, note
  assert "ran again (seed 1, 2), and its run from seed 2 placed 11 and agreed with the global model" in note, note
  record = sfm.mapping_record(best, note, choice, [first, glob] + choice["reruns"])
  assert record["kept"] == "global" and record["kept_seed"] == 0 and record["reason"] == "agreed with a rerun"
  assert [(r["mapper"], r["seed"], r.get("rerun", False)) for r in record["tried"]] == [
      ("incremental", 0, False), ("global", 0, False), ("incremental", 1, True), ("incremental", 2, True)]
  first_r, glob_r, wrong_r, right_r = record["tried"]
  assert glob_r["agreement_with_incremental"]["rotation_deg"] > 45 and not sfm.agrees(
      glob_r["agreement_with_incremental"])
  assert right_r["agreement_with_global"]["common"] == 11 and right_r["agreement_with_global"]["rotation_deg"] < 1e-4
  assert wrong_r["agreement_with_global"]["rotation_deg"] > 45
  # The figures of each model on the images it shares with the other: recorded, not used to decide.
  assert first_r["on_common_images"] == {"images": 10, "observations": 1000, "reprojection_error_px": 0.9,
                                         "track_length": 3.0}
  assert glob_r["on_common_images"]["images"] == 10 and glob_r["on_common_images"]["track_length"] == 5.0
  assert right_r["on_common_images"]["reprojection_error_px"] == 0.7
  json.dumps(record, allow_nan=False)  # prepare.json's, as written


def test_a_global_model_no_incremental_run_agrees_with_is_not_used():
  glob, first, reruns = _candidates()
  reruns[2] = dict(reruns[2], poses=_flipped(reruns[2]["poses"]), registered=9)
  best, note, choice = sfm.choose_model([first, glob], lambda k: dict(reruns[k]))
  # None agrees: the incremental run that placed the most (the rerun from seed 1, 11 images) is kept.
  assert best["mapper"] == "incremental" and best["seed"] == 1 and choice["reason"] == "disagreed"
  assert "nor did it agree with the incremental mapper's runs from seed 1, 2, so its model was not used; the run " \
      "from seed 1 placed the most (11)" in note, note
  record = sfm.mapping_record(best, note, choice, [first, glob] + choice["reruns"])
  assert record["kept"] == "incremental" and record["kept_seed"] == 1 and len(record["tried"]) == 4
  # Without reruns (a hand-made choice), the first incremental model is kept.
  glob, first, _ = _candidates()
  best, note, choice = sfm.choose_model([first, glob])
  assert best is first and choice == {"reason": "disagreed", "reruns": []} and note.endswith("was not used")


def test_derived_seeds_stay_in_colmaps_range():
  assert sfm.derived_seed(0, 0) == 0 and sfm.derived_seed(5, 2) == 7
  assert sfm.derived_seed(sfm.MAX_SEED, 1) == 0 and sfm.derived_seed(sfm.MAX_SEED - 1, 2) == 0


def test_too_few_message_suggests_what_was_not_tried():
  one = [{"mapper": "global", "registered": 3}]
  message = sfm.too_few_message(3, 40, 20, one, "sequential", "x.partial")
  assert "only 3 of 40" in message and "--matching=exhaustive" in message and "--mapper=incremental" in message
  both = one + [{"mapper": "incremental", "registered": 7}]
  message = sfm.too_few_message(7, 40, 20, both, "exhaustive", "x.partial")
  assert "--matching" not in message and "--mapper" not in message and "x.partial" in message


def test_eta_and_durations():
  assert progress.eta(10, 40, 5.0) == ", about 15 s left"
  assert progress.eta(0, 40, 5.0) == "" and progress.eta(40, 40, 5.0) == ""
  assert progress.duration(3.21) == "3.2 s" and progress.duration(125) == "2 min 5 s"


def test_photos_rotated_by_exif_are_written_upright(tmp_path):
  src = tmp_path / "photos"
  src.mkdir()
  for i in range(5):
    im = Image.fromarray(np.full((30, 40, 3), 40 * i, np.uint8))
    exif = im.getexif()
    exif[0x0112] = 6  # rotate 90 degrees clockwise to view
    exif[0x010F], exif[0x0110] = "Phone", "X"
    im.save(src / f"p {i}.jpg", exif=exif)
  source = frames.scan_input(str(src))
  assert source.sizes == [(30, 40)] * 5 and all(source.rotated) and source.makers == [("Phone", "X")] * 5
  names, info = frames.stage_images(source, str(tmp_path / "images"), 10)
  assert names == [f"p_{i}.jpg" for i in range(5)] and info["upright_copies"] == 5
  with Image.open(tmp_path / "images" / "p_0.jpg") as im:
    assert im.size == (30, 40) and im.getexif().get(0x0112, 1) == 1


# --------------------------------------------------------------------------------------------------------------
# Bad input: one sentence on stderr, exit code 2, no --out folder


def _bad(capsys, tmp_path, *args, match):
  out = tmp_path / "capture"
  code, _, err = run_prepare(capsys, *args, f"--out={out}")
  assert code == 2, err
  lines = err.strip().splitlines()
  assert len(lines) == 1 and lines[0].startswith("nerfpod: error: ") and "Traceback" not in err, err
  assert match in lines[0], lines[0]
  assert not out.exists() or not os.listdir(out)
  return lines[0]


def test_bad_inputs_are_one_sentence_and_exit_2(tmp_path, capsys):
  _bad(capsys, tmp_path, f"--input={tmp_path / 'nowhere'}", match="does not exist")
  empty = tmp_path / "empty"
  empty.mkdir()
  (empty / "notes.txt").write_text("x")
  _bad(capsys, tmp_path, f"--input={empty}", match="holds no images")
  heic = tmp_path / "heic"
  heic.mkdir()
  (heic / "IMG_1.HEIC").write_bytes(b"\0" * 10)
  _bad(capsys, tmp_path, f"--input={heic}", match="convert them to JPEG")
  few = tmp_path / "few"
  few.mkdir()
  for i in range(3):
    Image.new("RGB", (40, 30)).save(few / f"{i}.png")
  _bad(capsys, tmp_path, f"--input={few}", match="holds 3 image(s)")
  _bad(capsys, tmp_path, f"--input={few / '0.png'}", match="is a single image")
  clip = tmp_path / "clip.mp4"
  clip.write_bytes(b"not a video at all" * 100)
  line = _bad(capsys, tmp_path, f"--input={clip}", match="is not a video that ffmpeg can read")
  # ffmpeg's own last line (FFmpeg 7's wording, imageio-ffmpeg's binary), never cut mid-word
  assert "clip.mp4 is not a video that ffmpeg can read (Error opening input files: Invalid data found when " \
         "processing input); pass a folder" in line, line
  text = tmp_path / "notes.txt"
  text.write_text("hello")
  _bad(capsys, tmp_path, f"--input={text}", match="is not a video (or a folder of photos) that ffmpeg can read")
  short = tmp_path / "short.mp4"
  write_video(short, [np.full((64, 64, 3), 60 * i, np.uint8) for i in range(3)])
  _bad(capsys, tmp_path, f"--input={short}", match="gave only 3 frame(s), and structure from motion needs at least 5")
  assert not (tmp_path / "capture.partial").exists()  # the input's fault: no work kept
  cut = tmp_path / "cut.mp4"  # a copy that broke off (ffmpeg writes the index last, so it is lost)
  cut.write_bytes(short.read_bytes()[:short.stat().st_size // 2])
  _bad(capsys, tmp_path, f"--input={cut}", match="cut.mp4 is not a video that ffmpeg can read")
  mixed = tmp_path / "mixed"
  mixed.mkdir()
  for i in range(5):
    Image.new("RGB", (40, 30) if i else (30, 40)).save(mixed / f"{i}.png")
  _bad(capsys, tmp_path, f"--input={mixed}", "--cameras=shared", match="--cameras=shared needs images of one size")
  (mixed / "5.jpg").write_bytes(b"\xff\xd8 broken")
  _bad(capsys, tmp_path, f"--input={mixed}",
       match="5.jpg is damaged (cannot identify image file); remove it, or pass --skip_bad_images")


def test_an_out_folder_that_holds_something_else_is_refused(tmp_path, capsys):
  photos = tmp_path / "photos"
  photos.mkdir()
  for i in range(5):
    Image.new("RGB", (40, 30)).save(photos / f"{i}.png")
  other = tmp_path / "other"
  other.mkdir()
  (other / "thesis.tex").write_text("keep me")
  code, _, err = run_prepare(capsys, f"--input={photos}", f"--out={other}", "--overwrite")
  assert code == 2 and "already holds other files" in err and (other / "thesis.tex").exists()
  code, _, err = run_prepare(capsys, f"--input={photos}", f"--out={photos}")
  assert code == 2 and "is the input itself" in err
  (tmp_path / "afile").write_text("x")
  code, _, err = run_prepare(capsys, f"--input={photos}", f"--out={tmp_path / 'afile'}")
  assert code == 2 and "is a file; pass a folder path" in err


def _jpegs(folder, n, truncate=()):
  """n JPEG photos of the textured scene (160x120) in `folder`; those indexed in `truncate` cut to their first
  half, as a copy that broke off."""
  folder.mkdir(parents=True)
  for i, c2w in enumerate(ring_poses(n)):
    path = folder / f"photo_{i:02d}.jpg"
    Image.fromarray(render_textured(c2w, 160, 120, 144.0)).save(path, quality=95)
    if i in truncate:
      data = path.read_bytes()
      path.write_bytes(data[:len(data) // 2])
  return folder


def _no_features(*args, **kwargs):
  raise AssertionError("feature extraction started")


def test_a_damaged_photo_is_named_before_any_feature_extraction(tmp_path, capsys, monkeypatch):
  monkeypatch.setattr(sfm, "stage_features", _no_features)
  photos = _jpegs(tmp_path / "photos", 6, truncate=(3,))
  out = tmp_path / "a" / "capture"
  start = time.monotonic()
  code, stdout, err = run_prepare(capsys, f"--input={photos}", f"--out={out}")
  assert code == 2 and "Traceback" not in err and err.count("\n") == 1, err
  assert err.startswith(f"nerfpod: error: {photos / 'photo_03.jpg'} is damaged (image file is truncated"), err
  assert err.rstrip().endswith("; remove it, or pass --skip_bad_images to go on without it."), err
  assert time.monotonic() - start < 10 and "[2/5]" not in stdout
  assert not (tmp_path / "a").exists()  # no --out, no work folder, not even the folder above them
  # A rerun says the same (nothing was kept that would hide it), and several are one sentence.
  assert run_prepare(capsys, f"--input={photos}", f"--out={out}")[2] == err
  (photos / "photo_04.jpg").write_bytes(b"\xff\xd8 not a jpeg at all")
  code, _, err = run_prepare(capsys, f"--input={photos}", f"--out={out}")
  assert code == 2 and err.count("\n") == 1, err
  assert f"2 images in {photos} are damaged: photo_03.jpg (image file is truncated" in err
  assert "photo_04.jpg (cannot identify image file)" in err and "remove them, or pass --skip_bad_images" in err


def test_skip_bad_images_leaves_the_damaged_photos_out(tmp_path, capsys, monkeypatch):
  photos = _jpegs(tmp_path / "photos", 7, truncate=(1, 5))
  out = tmp_path / "capture"

  def stop(db_path, image_dir, names, *args):
    assert names == [f"photo_{i:02d}.jpg" for i in (0, 2, 3, 4, 6)] == sorted(os.listdir(image_dir))
    raise KeyboardInterrupt
  monkeypatch.setattr(sfm, "stage_features", stop)
  code, stdout, err = run_prepare(capsys, f"--input={photos}", f"--out={out}", "--skip_bad_images")
  assert code == 130, err
  warning, interrupted = err.strip().splitlines()
  assert warning.startswith(f"nerfpod: warning: leaving out 2 damaged image(s) in {photos} (--skip_bad_images): "
                            f"photo_01.jpg (image file is truncated"), warning
  assert "photo_05.jpg (" in warning and "the same command resumes" in interrupted
  assert "linking 5 photos" in stdout
  # Where too few are left, the too-few sentence says why.
  (photos / "photo_06.jpg").unlink()
  code, _, err = run_prepare(capsys, f"--input={photos}", f"--out={out}", "--skip_bad_images", "--overwrite")
  assert code == 2 and "holds 4 image(s) (after leaving out 2 damaged), and structure from motion needs at " \
      "least 5" in err, err


def test_damaged_photos_decision(tmp_path):
  """check_photos: what decodes stays; a truncated JPEG or PNG, or a file that is no image, is damaged; the
  sentence names at most MAX_NAMED of them; PIL's LOAD_TRUNCATED_IMAGES, where something turned it on, is off
  while checking and restored after."""
  from PIL import ImageFile
  folder = _jpegs(tmp_path / "p", 6, truncate=(0,))
  Image.fromarray(render_textured(ring_poses(1)[0], 160, 120, 144.0)).save(folder / "z.png")
  data = (folder / "z.png").read_bytes()
  (folder / "z.png").write_bytes(data[:len(data) // 2])
  assert frames.decode_error(str(folder / "photo_01.jpg")) is None
  assert "truncated" in frames.decode_error(str(folder / "photo_00.jpg"))
  assert frames.decode_error(str(folder / "z.png"))
  ImageFile.LOAD_TRUNCATED_IMAGES = True
  try:
    src = frames.scan_input(str(folder))
    with pytest.raises(UserError, match=r"2 images in .* are damaged: photo_00.jpg \(image file is truncated"):
      frames.check_photos(src, skip_bad=False, threads=2)
    assert ImageFile.LOAD_TRUNCATED_IMAGES
  finally:
    ImageFile.LOAD_TRUNCATED_IMAGES = False
  warning = frames.check_photos(src, skip_bad=True)
  assert src.files == [f"photo_{i:02d}.jpg" for i in range(1, 6)] and len(src.sizes) == len(src.rotated) == 5
  assert "leaving out 2 damaged image(s)" in warning and "photo_00.jpg (" in warning and "z.png (" in warning
  many = {f"{i}.jpg": "image file is truncated" for i in range(8)}
  message = frames.damaged_message("dir", many)
  assert message.startswith("8 images in dir are damaged: 0.jpg (image file is truncated), ") and \
      "4.jpg (image file is truncated) and 3 more; remove them" in message and "5.jpg" not in message


def test_an_out_that_cannot_be_written_is_one_sentence_before_any_work(tmp_path, capsys, monkeypatch):
  monkeypatch.setattr(sfm, "stage_features", _no_features)
  photos = _jpegs(tmp_path / "photos", 5)
  (tmp_path / "afile").write_text("x")
  for out in (tmp_path / "afile" / "capture", tmp_path / "afile" / "deeper" / "capture"):
    code, stdout, err = run_prepare(capsys, f"--input={photos}", f"--out={out}")
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert f"--out {out} is inside {tmp_path / 'afile'}, which is a file, not a folder; pass a folder path" in err
    assert (tmp_path / "afile").read_text() == "x" and stdout == ""
  # A folder this user may not write (as root, permissions do not bite: the probe is made to fail instead).
  locked = tmp_path / "locked"
  locked.mkdir()
  if os.geteuid() != 0:
    locked.chmod(0o500)
  else:
    def refused(folder):
      raise PermissionError(13, "Permission denied", folder)
    monkeypatch.setattr(prepare, "_probe", refused)
  try:
    code, stdout, err = run_prepare(capsys, f"--input={photos}", f"--out={locked / 'new' / 'capture'}")
  finally:
    locked.chmod(0o700)
  assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
  assert f"--out {locked / 'new' / 'capture'} cannot be written (Permission denied); pass a folder path" in err
  assert os.listdir(locked) == [] and stdout == ""


def test_the_out_probe_leaves_nothing(tmp_path):
  prepare._probe(str(tmp_path / "a" / "b"))
  assert os.listdir(tmp_path) == []


@needs_pycolmap
def test_too_few_images_registered_keeps_the_work_for_a_rerun(tmp_path, capsys):
  noise = tmp_path / "noise"
  noise.mkdir()
  rng = np.random.default_rng(0)
  for i in range(6):
    Image.fromarray(rng.integers(0, 255, (96, 128, 3), dtype=np.uint8)).save(noise / f"{i}.png")
  out = tmp_path / "capture"
  code, stdout, err = run_prepare(capsys, f"--input={noise}", f"--out={out}")
  assert code == 2 and err.count("\n") == 1, err
  assert "only 0 of 6 images could be placed (the incremental mapper 0, the global mapper 0)" in err
  assert "trying the global mapper" in stdout
  assert not out.exists() and (tmp_path / "capture.partial" / "database.db").is_file()


# --------------------------------------------------------------------------------------------------------------
# End to end


@pytest.fixture(scope="module")
def textured(tmp_path_factory):
  """24 photos (160x120) of the textured scene around a ring, and their known poses by file name."""
  root = tmp_path_factory.mktemp("textured")
  poses = ring_poses(24)
  write_photos(root / "photos", poses)
  return root, {f"view_{i:03d}.png": p for i, p in enumerate(poses)}


@needs_pycolmap
def test_photos_to_a_capture_that_all_three_loaders_read(textured, tmp_path, capsys):
  from nerfpod.scenes import colmap, detect, llff, nerfstudio
  root, known = textured
  out = tmp_path / "capture"
  start = time.monotonic()
  code, stdout, err = run_prepare(capsys, f"--input={root / 'photos'}", f"--out={out}")
  seconds = time.monotonic() - start
  assert code == 0, err
  assert f"nerfpod train --config=configs/capture.py:path={out}" in stdout
  assert "registered 24 of 24 images (incremental mapper)" in stdout and "mean reprojection error" in stdout
  assert sorted(os.listdir(out)) == ["images", "poses_bounds.npy", "prepare.json", "sparse", "transforms.json"]
  assert not (tmp_path / "capture.partial").exists()
  summary = json.loads((out / "prepare.json").read_text())
  assert summary["counts"]["registered"] == 24 and summary["options"]["matching"] == "exhaustive"
  assert summary["options"]["cameras"] == "shared" and not summary["forward_facing"]
  assert detect(str(out)) == "colmap"  # what data.kind=auto (configs/capture.py) reads
  scene = colmap.load(str(out), capture_config(out).data)
  rotation, position = pose_errors(scene_poses(scene), known)
  print(f"textured photos: 24 of 24 registered in {seconds:.1f} s; rotation error median "
        f"{np.median(rotation):.2f} max {rotation.max():.2f} degrees; camera centre error median "
        f"{100 * np.median(position):.2f}% max {100 * position.max():.2f}%")
  assert np.median(rotation) < 1.0 and rotation.max() < 3.0
  assert np.median(position) < 0.02 and position.max() < 0.05
  fx = scene.split("train").cameras.fx
  assert np.allclose(fx, 144.0, rtol=0.03)  # the renders' focal length
  # transforms.json gives the same cameras (nerfpod's nerfstudio loader normalises the same way)
  other = nerfstudio.load(str(out), capture_config(out).data)
  again = scene_poses(other)
  assert max(np.abs(again[k] - v).max() for k, v in scene_poses(scene).items()) < 1e-4
  # and poses_bounds.npy the same camera centres and orientations, in LLFF's frame
  data = capture_config(out).data
  data.kind = "llff"
  rotation, position = pose_errors(scene_poses(llff.load(str(out), data)), known)
  assert np.median(rotation) < 1.0 and np.median(position) < 0.02


@needs_pycolmap
def test_video_frames_are_the_sharp_ones_and_get_poses(textured, tmp_path, capsys):
  from nerfpod.scenes import colmap
  poses = ring_poses(24)
  video_frames = []
  for c2w in poses:  # each view blurred, sharp, blurred: the window of 3 must give the sharp one
    sharp = Image.fromarray(render_textured(c2w, 160, 128, 144.0))
    blurred = np.asarray(sharp.filter(ImageFilter.GaussianBlur(1.5)))
    video_frames += [blurred, np.asarray(sharp), blurred]
  video = tmp_path / "orbit.mp4"
  write_video(video, video_frames)
  out = tmp_path / "capture"
  code, stdout, err = run_prepare(capsys, f"--input={video}", f"--out={out}", "--num_frames=24")
  assert code == 0, err
  assert "took 24 frames of 72" in stdout and "matching: sequential" in stdout
  summary = json.loads((out / "prepare.json").read_text())
  assert summary["input"]["video_frames"] == 72 and summary["input"]["taken"] == 24
  assert sorted(os.listdir(out / "images")) == [f"frame_{3 * k + 1:06d}.jpg" for k in range(24)]
  scene = colmap.load(str(out), capture_config(out).data)
  known = {f"frame_{3 * k + 1:06d}.jpg": p for k, p in enumerate(poses)}
  rotation, position = pose_errors(scene_poses(scene), known)
  print(f"textured video: {len(scene_poses(scene))} of 24 registered; rotation error median "
        f"{np.median(rotation):.2f} degrees; camera centre error median {100 * np.median(position):.2f}%")
  assert len(scene_poses(scene)) == 24 and np.median(rotation) < 1.0 and np.median(position) < 0.02


def _written(out) -> dict:
  """What a capture's poses, cameras and points come to: the bytes of its poses_bounds.npy and transforms.json, the
  camera-to-world poses by name in sparse/0/, and prepare.json."""
  import pycolmap
  rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
  return {"poses_bounds": (out / "poses_bounds.npy").read_bytes(), "transforms": (out / "transforms.json").read_text(),
          "poses": sfm.camera_poses(rec), "points": rec.num_points3D(),
          "cameras": {i: list(c.params) for i, c in rec.cameras.items()},
          "summary": json.loads((out / "prepare.json").read_text())}


# The incremental mapper's case failed 2 of its 12 runs on 2026-12-06 (a later run's poses not the first's bit for
# bit). The likely cause, found on 2026-12-07: COLMAP's CPU matcher shares the draws of FLANN's randomised k-d trees
# between its threads, so which pairs a thread took changed the matches (44 phone photos matched 4 times on 2
# threads: 4 different match tables). Matching runs on one thread since (sfm.seeded_options), and the case fails
# as any test (its message says from which stage on two runs parted).


@needs_pycolmap
def test_the_steps_whose_result_thread_timing_could_change_run_on_one_thread():
  """Matching (FLANN's shared draws), the verification's RANSAC and both mappers run on one thread whatever
  --threads says; SIFT, each image alone, on as many as it says."""
  assert sfm.seeded_options("extraction", 0, threads=8).num_threads == 8
  assert sfm.seeded_options("matching", 0, threads=8).num_threads == 1
  assert sfm.seeded_options("matching", 0).sift.cpu_brute_force_matcher is False  # (FLANN: 10 times quicker)
  assert sfm.seeded_options("verification", 3, threads=8).ransac.num_threads == 1
  assert sfm.seeded_options("verification", 3).ransac.random_seed == 3
  for mapper in ("incremental", "global"):
    options = sfm.seeded_options(mapper, 5, threads=8)
    assert options.num_threads == 1 and options.random_seed == 5


def _database_digests(db_path) -> dict:
  """A digest of each table of a COLMAP database that a stage writes (the images' cameras, the features, the
  matches, the verified pairs), each read in its key's order."""
  import hashlib
  import sqlite3
  tables = {"cameras": "camera_id", "images": "image_id", "keypoints": "image_id", "descriptors": "image_id",
            "matches": "pair_id", "two_view_geometries": "pair_id"}
  con = sqlite3.connect(db_path)
  try:
    return {t: hashlib.sha1(repr(con.execute(f"SELECT * FROM {t} ORDER BY {key}").fetchall()).encode()).hexdigest()
            for t, key in tables.items()}
  finally:
    con.close()


@needs_pycolmap
@pytest.mark.parametrize("mapper", ["auto", "global"])
def test_the_same_photos_and_seed_give_the_same_capture(textured, tmp_path, capsys, monkeypatch, mapper):
  """Two runs on the same photos with 2 threads, and (the incremental mapper) a third with 1: the same images
  registered and the same poses, cameras and points, bit for bit; prepare.json records the seed. Where they
  differ, the message says from which stage on: the database's tables as the mapping stage found them, and each
  mapper run's poses."""
  root, _ = textured
  digests, mapped = [], []
  real_stage, real_mapper = sfm.stage_mapping, sfm.run_mapper

  def stage_mapping(db_path, *args, **kwargs):
    digests.append(_database_digests(db_path))
    return real_stage(db_path, *args, **kwargs)

  def run_mapper(mapper, *args, **kwargs):
    result = real_mapper(mapper, *args, **kwargs)
    mapped[-1].append((mapper, result["seed"], result["poses"]))
    return result
  monkeypatch.setattr(sfm, "stage_mapping", stage_mapping)
  monkeypatch.setattr(sfm, "run_mapper", run_mapper)
  threads_of = (2, 2, 1) if mapper == "auto" else (2, 2)
  runs = []
  for i, threads in enumerate(threads_of):
    out = tmp_path / f"capture{i}"
    mapped.append([])
    code, stdout, err = run_prepare(capsys, f"--input={root / 'photos'}", f"--out={out}", f"--threads={threads}",
                                    f"--mapper={mapper}")
    assert code == 0, err
    assert f"({threads} threads, seed 0; work in" in stdout
    runs.append(_written(out))
  first = runs[0]
  assert first["summary"]["options"]["seed"] == 0 and first["summary"]["mapping"]["kept_seed"] == 0
  assert len(first["poses"]) >= 20
  for n, again in enumerate(runs[1:], start=1):
    problem = _parted(first, again, digests[0], digests[n], mapped[0], mapped[n],
                      f"run {n + 1} ({threads_of[n]} threads)")
    assert not problem, problem


def _parted(first, again, digests_first, digests_again, mapped_first, mapped_again, label) -> str:
  """'' where two prepare runs wrote the same capture bit for bit (_written), else what differs and from which
  stage on: the database's tables as the mapping stage found them, and each mapper run's poses."""
  tables = [t for t in digests_first if digests_again[t] != digests_first[t]]
  runs_differ = [f"{m} (seed {s})" for (m, s, p), (m0, s0, p0) in zip(mapped_again, mapped_first)
                 if (m, s) != (m0, s0) or sorted(p) != sorted(p0) or not all(np.array_equal(p[k], p0[k]) for k in p0)]
  where = (f"the database's {', '.join(tables)} differ before mapping" if tables else
           f"the database is the same; the mapper runs that differ: {', '.join(runs_differ) or 'none'} (run 1: "
           f"{[(m, s) for m, s, _ in mapped_first]}, this run: {[(m, s) for m, s, _ in mapped_again]})")
  if sorted(again["poses"]) != sorted(first["poses"]):
    return f"{label} registered other images; {where}"
  differ = {k: float(np.max(np.abs(again["poses"][k] - first["poses"][k]))) for k in first["poses"]
            if not np.array_equal(again["poses"][k], first["poses"][k])}
  if differ:
    return (f"{label} differs from run 1 in {len(differ)} poses, by up to {max(differ.values()):.3g}; kept: "
            f"{again['summary']['mapping']['kept']} against {first['summary']['mapping']['kept']}; {where}")
  for key in ("cameras", "points", "poses_bounds", "transforms"):
    if again[key] != first[key]:
      return f"{label} wrote other {key}; {where}"
  if again["summary"]["counts"] != first["summary"]["counts"]:
    return f"{label} counted otherwise ({again['summary']['counts']}); {where}"
  if tables or runs_differ:
    return f"{label} wrote the same capture, but {where}"
  return ""


@needs_pycolmap
def test_another_seed_is_taken_and_recorded_and_a_bad_one_refused(textured, tmp_path, capsys):
  root, _ = textured
  out = tmp_path / "capture"
  code, stdout, err = run_prepare(capsys, f"--input={root / 'photos'}", f"--out={out}", "--seed=7")
  assert code == 0, err
  summary = json.loads((out / "prepare.json").read_text())
  assert summary["options"]["seed"] == 7 and summary["mapping"]["kept_seed"] == 7
  assert [r["seed"] for r in summary["mapping"]["tried"]] == [7] and summary["counts"]["registered"] == 24
  for bad in ("-1", str(sfm.MAX_SEED + 1), "one"):
    code, stdout, err = run_prepare(capsys, f"--input={root / 'photos'}", f"--out={tmp_path / 'other'}",
                                    f"--seed={bad}")
    assert code == 2 and err.count("\n") == 1 and err.startswith(f"nerfpod: error: --seed={bad}: "), err
    assert "Traceback" not in err and not (tmp_path / "other").exists()


@needs_pycolmap
def test_a_disagreement_reruns_the_incremental_mapper_and_prepare_json_says_so(textured, tmp_path, capsys,
                                                                                monkeypatch):
  """The first incremental model made to disagree (16 of its cameras turned upside down, the other 8 left out):
  the global mapper runs, disagrees with it, and the incremental mapper runs again from seed 1, whose model agrees
  with the global one; prepare.json records the three runs and why the kept model won."""
  root, _ = textured
  real = sfm.run_mapper

  def run_mapper(mapper, db_path, image_dir, out_dir, num_images, seed=0):
    result = real(mapper, db_path, image_dir, out_dir, num_images, seed)
    if mapper == "incremental" and os.path.basename(out_dir) == "sparse_incremental":
      kept = sorted(result["poses"])[:16]
      result.update(registered=16, poses=_flipped({k: result["poses"][k] for k in kept}))
    return result
  monkeypatch.setattr(sfm, "run_mapper", run_mapper)
  out = tmp_path / "capture"
  code, stdout, err = run_prepare(capsys, f"--input={root / 'photos'}", f"--out={out}")
  assert code == 0, err
  assert "trying the global mapper" in stdout and "running the incremental mapper again from seed 1" in stdout
  mapping = json.loads((out / "prepare.json").read_text())["mapping"]
  assert mapping["reason"] == "agreed with a rerun", mapping
  assert [(r["mapper"], r["seed"], r.get("rerun", False)) for r in mapping["tried"]] == [
      ("incremental", 0, False), ("global", 0, False), ("incremental", 1, True)]
  first, glob, rerun = mapping["tried"]
  assert not sfm.agrees(first["agreement_with_global"]) and sfm.agrees(rerun["agreement_with_global"])
  assert glob["agreement_with_incremental"] == first["agreement_with_global"]
  for figures in (rerun["on_common_images"], rerun["global_on_common_images"]):  # from the real models
    assert figures["images"] >= 20 and 0 < figures["reprojection_error_px"] < 2 and figures["track_length"] >= 2
  assert (mapping["kept"], mapping["kept_seed"]) in (("global", 0), ("incremental", 1))
  assert "and its run from seed 1 placed" in mapping["note"] and "agreed with the global model" in mapping["note"]
  assert f"({mapping['kept']} mapper; the global mapper placed" in stdout


@needs_pycolmap
def test_an_interrupted_run_resumes_and_overwrite_starts_again(textured, tmp_path, capsys, monkeypatch):
  root, _ = textured
  out = tmp_path / "capture"
  args = (f"--input={root / 'photos'}", f"--out={out}")

  def interrupt(*a, **k):
    raise KeyboardInterrupt
  with monkeypatch.context() as m:
    m.setattr(sfm, "stage_matching", interrupt)
    code, _, err = run_prepare(capsys, *args)
  assert code == 130 and "the same command resumes" in err
  assert not out.exists() and (tmp_path / "capture.partial" / "database.db").is_file()
  code, stdout, err = run_prepare(capsys, *args)
  assert code == 0, err
  assert "24 of 24 images have their features from an earlier run" in stdout
  code, _, err = run_prepare(capsys, *args)
  assert code == 2 and "already holds a prepared capture; pass --overwrite" in err
  code, stdout, err = run_prepare(capsys, *args, "--overwrite", "--mapper=global")
  assert code == 0, err
  assert "earlier run" not in stdout, stdout
  # How many images the global mapper registers is the same every run (one seed, one thread) but may differ from
  # one machine to another (docs/prepare.md); which mapper was kept may not.
  assert re.search(r"\b2[0-4] of 24 images \(global mapper", stdout), stdout
  assert json.loads((out / "prepare.json").read_text())["mapping"]["kept"] == "global"


@needs_pycolmap
@pytest.mark.slow  # two prepares of 40 horns photos (the quick loop runs twice on the synthetic photos, whose
# poses it checks against the renders' own: test_photos_to_a_capture_that_all_three_loaders_read)
def test_the_horns_photos_agree_with_the_published_poses_and_give_the_same_capture_twice(tmp_path, capsys):
  """40 of the LLFF horns images (252x189), prepared twice with the same (default) seed, once on 2 threads and
  once on 1: a forward-facing capture whose poses agree with those LLFF published (COLMAP on the full-size
  images); the same images registered, the same poses and points, bit for bit."""
  from nerfpod.scenes import colmap, llff
  folder = require(DATA / "llff_horns")
  names = sorted(os.listdir(folder / "images_8"))
  published, _, _ = llff.read_poses_bounds(str(folder / "poses_bounds.npy"))
  photos = tmp_path / "photos"
  photos.mkdir()
  pick = np.round(np.linspace(0, len(names) - 1, 40)).astype(int)
  for i in pick:
    Image.open(folder / "images_8" / names[i]).convert("RGB").reduce(2).save(photos / names[i])
  runs = []
  for i, threads in enumerate((2, 1)):
    out = tmp_path / f"capture{i}"
    start = time.monotonic()
    code, stdout, err = run_prepare(capsys, f"--input={photos}", f"--out={out}", f"--threads={threads}")
    seconds = time.monotonic() - start
    assert code == 0, err
    runs.append(_written(out))
  assert "forward-facing" in stdout and f"--config=configs/llff.py --config.data.path={out}" in stdout
  rotation, position = pose_errors(scene_poses(colmap.load(str(out), capture_config(out).data)),
                                   {names[i]: published[i] for i in pick})
  print(f"horns: {len(rotation)} of 40 registered in {seconds:.1f} s; rotation error median "
        f"{np.median(rotation):.2f} max {rotation.max():.2f} degrees; camera centre error median "
        f"{100 * np.median(position):.2f}% max {100 * position.max():.2f}%")
  assert len(rotation) == 40 and np.median(rotation) < 0.5 and np.median(position) < 0.03
  first, again = runs
  assert len(first["poses"]) >= 36 and sorted(again["poses"]) == sorted(first["poses"])
  assert all(np.array_equal(again["poses"][k], first["poses"][k]) for k in first["poses"])
  assert again["cameras"] == first["cameras"] and again["points"] == first["points"]
  assert again["poses_bounds"] == first["poses_bounds"]


# The cup at 400x300 in every run; at its own 800x600 (3.5-5 min on 2 cores, the longest test by far) only
# where NERFPOD_TEST_FULL_SFM=1 asks for it: the same pipeline on the same photos, with tighter bounds.
CUP_SIZES = [(2, 3.5, 0.07)] + ([(1, 2.0, 0.05)] if os.environ.get("NERFPOD_TEST_FULL_SFM") == "1" else [])


@needs_pycolmap
@pytest.mark.slow
@pytest.mark.parametrize("shrink,max_degrees,max_centre", CUP_SIZES)
def test_cup_photos_agree_with_the_shared_model(tmp_path, capsys, shrink, max_degrees, max_centre):
  """The shared COLMAP cup's 77 images at 400x300 (20-30 s; and at their 800x600 with NERFPOD_TEST_FULL_SFM=1):
  95% registered or more; after a similarity alignment the median rotation error and the median camera-centre
  error (as a share of the cameras' mean distance from their centroid) within bounds. The shared model, made on
  the 800x600 images with per-image cameras, is a reference, not the truth; at 400x300 SIFT finds fewer,
  less precise features."""
  import pycolmap
  from nerfpod.scenes import colmap
  folder = require(DATA / "colmap_cup")
  reference = pycolmap.Reconstruction(str(folder / "sparse" / "0"))
  known = {}
  for im in reference.images.values():
    w2c = np.concatenate([np.asarray(im.cam_from_world().matrix()), [[0, 0, 0, 1.0]]])
    known[im.name] = np.linalg.inv(w2c) @ capture.OPENCV_TO_OPENGL
  photos = folder / "images"  # exactly the model's 77 images
  if shrink > 1:
    photos = tmp_path / "photos"
    photos.mkdir()
    for name in known:
      Image.open(folder / "images" / name).reduce(shrink).save(photos / name, quality=95)
  out = tmp_path / "capture"
  start = time.monotonic()
  code, stdout, err = run_prepare(capsys, f"--input={photos}", f"--out={out}")
  seconds = time.monotonic() - start
  assert code == 0, err
  assert sorted(os.listdir(out / "images_2")) == sorted(os.listdir(out / "images"))
  assert (out / "images_4").exists() == (shrink == 1)  # images_N while the long side stays >= 200 pixels
  rotation, position = pose_errors(scene_poses(colmap.load(str(out), capture_config(out).data)), known)
  print(f"cup at 1/{shrink}: {len(rotation)} of {len(known)} registered in {seconds:.1f} s; rotation error median "
        f"{np.median(rotation):.2f} max {rotation.max():.2f} degrees; camera centre error median "
        f"{100 * np.median(position):.2f}% max {100 * position.max():.2f}%")
  assert len(rotation) >= 0.95 * len(known)
  assert np.median(rotation) < max_degrees and np.median(position) < max_centre


@needs_pycolmap
@pytest.mark.slow
def test_a_horns_video_prepares_into_a_capture_llff_trains_on(tmp_path, capsys):
  """31 horns images as a video (496x368): prepare, then configs/llff.py:smoke trains, evaluates and renders."""
  from procs import run_main
  folder = require(DATA / "llff_horns")
  names = sorted(os.listdir(folder / "images_8"))[::2]
  video_frames = [np.asarray(Image.open(folder / "images_8" / n).convert("RGB").resize((496, 368), Image.BILINEAR))
            for n in names]
  video = tmp_path / "horns.mp4"
  write_video(video, video_frames, fps=2)
  out = tmp_path / "capture"
  code, stdout, err = run_prepare(capsys, f"--input={video}", f"--out={out}", f"--num_frames={len(names)}")
  assert code == 0, err
  summary = json.loads((out / "prepare.json").read_text())
  assert summary["counts"]["registered"] >= 0.9 * len(names) and summary["forward_facing"]
  workdir = tmp_path / "run"
  result = run_main("--config=configs/llff.py:smoke", f"--config.data.path={out}", f"--workdir={workdir}",
                    "--config.train.num_steps=10", "--config.eval.max_views=1", "--config.orbit.num_frames=3",
                    timeout=600)
  assert result.returncode == 0, result.stderr[-3000:]
  # It evaluated the capture's first held-out frame at step 10, trained (the loss fell from step 1 to 10),
  # and rendered a complete 3-frame orbit at the capture's framing.
  metrics = json.loads((workdir / "eval" / "metrics.json").read_text())
  assert metrics["step"] == 10 and metrics["split"] == "test" and [v["index"] for v in metrics["views"]] == [0]
  assert np.isfinite(metrics["mean"]["psnr"]) and metrics["mean"]["psnr"] == metrics["views"][0]["psnr"]
  from tensorboard.backend.event_processing import event_accumulator
  events = event_accumulator.EventAccumulator(str(workdir), size_guidance={"scalars": 0})
  events.Reload()
  losses = {e.step: e.value for e in events.Scalars("train/loss")}
  print(f"horns video: losses {losses}, held-out PSNR {metrics['mean']['psnr']:.2f} dB")
  assert losses[10] < losses[1], losses
  from nerfpod.render import archive as archives
  orbit = archives.Archive.open(str(workdir / "renders" / "orbit.zarr"))
  assert orbit.num_frames == 3 and orbit.missing_frames() == []


def test_ffmpeg_reason_is_its_last_line_without_the_demuxer_prefix_cut_between_words():
  from nerfpod.prepare import frames
  error = RuntimeError("Could not load meta information\n=== stderr ===\nffmpeg version 7\n"
                       "[mov,mp4,m4a,3gp,3g2,mj2 @ 0x558bb5b20cc0] moov atom not found\n")
  assert frames.ffmpeg_reason(error) == "moov atom not found"
  long = RuntimeError("[in#0 @ 0x55ba7ed2c040] " + " ".join(f"word{i}" for i in range(60)))
  reason = frames.ffmpeg_reason(long, limit=50)
  assert reason == "word0 word1 word2 word3 word4 word5 word6 word7 ..." and len(reason) <= 54
  assert frames.ffmpeg_reason(OSError()) == "OSError"


def test_a_capture_with_under_90_percent_placed_ends_with_one_sentence_naming_those_left_out():
  import nerfpod.prepare as prepare_tool
  names = [f"{i:02d}.jpg" for i in range(44)]
  summary = {"counts": {"images": 44, "registered": 30, "unregistered": names[30:]},
             "options": {"seed": 0, "matching": "sequential"},
             "mapping": {"kept": "incremental", "tried": [{"mapper": "incremental"}]}}
  warning = prepare_tool.left_out_warning(summary)
  assert warning == ("nerfpod: warning: only 30 of 44 photos were placed (under 90%); left out: 30.jpg, 31.jpg, "
                     "32.jpg, 33.jpg, 34.jpg, 35.jpg, 36.jpg, 37.jpg, 38.jpg, 39.jpg and 4 more; try --seed=1, "
                     "--matching=exhaustive, --mapper=global with --overwrite (or another --out), or photos with "
                     "more overlap of those parts of the scene."), warning
  assert "\n" not in warning and warning.count(". ") == 0
  summary["counts"].update(registered=40, unregistered=names[40:])  # 40 of 44: 91%, no sentence
  assert prepare_tool.left_out_warning(summary) is None
  summary["counts"].update(registered=39, unregistered=names[39:])
  summary["options"].update(seed=7, matching="exhaustive")
  summary["mapping"] = {"kept": "global", "tried": [{"mapper": "global"}]}  # --mapper=global
  assert prepare_tool.left_out_warning(summary).endswith(
      "left out: 39.jpg, 40.jpg, 41.jpg, 42.jpg, 43.jpg; try --seed=8, --mapper=incremental with --overwrite (or "
      "another --out), or photos with more overlap of those parts of the scene.")
  # Both mappers ran (and a rerun): the other mapper is no longer something to try, as in too_few_message.
  summary["mapping"]["tried"] = [{"mapper": "incremental"}, {"mapper": "global"}, {"mapper": "incremental"}]
  assert "try --seed=8 with --overwrite" in prepare_tool.left_out_warning(summary)
