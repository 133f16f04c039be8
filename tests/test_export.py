"""Exporting an orbit archive: colour maps, videos read back, the contact sheet, refusing partial archives."""
import types

import imageio.v2 as imageio
import numpy as np
import pytest

from nerfpod.render import archive as archives
from nerfpod.render import video
from nerfpod.run import orbit
from nerfpod.errors import UserError
from nerfpod.nerf import cameras, compositing
from nerfpod import export as export_tool

NEAR, FAR = 2.0, 6.0
# Reading an mp4 back starts ffmpeg as a child process, which JAX (imported by other tests) warns about.
pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning:subprocess")  # (by category and module)


def _frame(index: int, num_frames: int, height: int, width: int) -> dict:
  """A smooth synthetic frame: a colour gradient that moves with the index; depth from near to far."""
  rows, cols = np.meshgrid(np.linspace(0, 1, height), np.linspace(0, 1, width), indexing="ij")
  phase = index / num_frames
  rgb = np.stack([rows, cols, np.full_like(rows, phase)], -1)
  depth = NEAR + (FAR - NEAR) * (cols + phase) / (1 + phase)
  acc = np.ones_like(rows)
  return {"rgb": video.to_uint8(rgb), "depth": depth.astype(np.float32), "acc": acc.astype(np.float32),
          "disparity": (acc / depth).astype(np.float32)}


def _archive(path, num_frames: int, height: int, width: int, frames=None) -> archives.Archive:
  intr = cameras.Intrinsics.from_focal(width, height, 20.0)
  attributes = {"num_frames": num_frames, "step": 1, "scene": "synthetic", "near": NEAR, "far": FAR,
                "fps": 10.0, "intrinsics": archives.intrinsics_json(intr),
                "poses": orbit.orbit_poses(num_frames, -30, 4).astype(float).tolist(), "config": {}}
  archive = archives.Archive.create(str(path), attributes)
  for i in range(num_frames) if frames is None else frames:
    archive.write_frame(i, _frame(i, num_frames, height, width), process_index=0)
  return archive


def test_turbo_runs_from_blue_through_green_to_red():
  colours = video.turbo(np.array([0.0, 0.15, 0.45, 0.9, 1.0, -3.0, 7.0]))
  assert colours.shape == (7, 3) and colours.min() >= 0 and colours.max() <= 1
  low, blue, green, red, high = colours[:5]
  for colour, channel in ((low, 2), (blue, 2), (green, 1), (red, 0), (high, 0)):
    assert colour[channel] == colour.max()
  assert low.sum() < 0.8 and high.sum() < 0.8  # dark at both ends
  # The ends of the published turbo table (its first and last entries), to the fit's accuracy.
  np.testing.assert_allclose(colours[[0, 4]], [[0.19, 0.07, 0.23], [0.48, 0.02, 0.01]], atol=0.12)
  np.testing.assert_array_equal(colours[5], low)  # clipped into [0, 1]
  np.testing.assert_array_equal(colours[6], high)


def test_depth_and_disparity_colours_show_near_warm_and_far_cold():
  frame = _frame(0, 1, 8, 40)  # depth grows from left (near) to right (far)
  style = video.ChannelStyle.fit([frame], NEAR, FAR)
  for channel in ("depth", "disparity"):
    image = style.image(channel, frame).astype(int)
    near_pixel, far_pixel = image[4, 0], image[4, -1]
    assert near_pixel[0] > near_pixel[2] and far_pixel[2] > far_pixel[0], channel
  # Where nothing is hit (acc 0) depth fades to black.
  empty = dict(frame, acc=np.zeros_like(frame["acc"]))
  assert style.image("depth", empty).max() == 0
  np.testing.assert_array_equal(style.image("acc", frame), 255)


@pytest.mark.parametrize("height,width", [(24, 32), (15, 21)])
def test_exported_videos_have_every_frame_at_the_archive_size(tmp_path, height, width):
  num_frames = 6
  _archive(tmp_path / "orbit.zarr", num_frames, height, width)
  files = export_tool.write_files(str(tmp_path / "orbit.zarr"), str(tmp_path / "out"), fps=12,
                                 formats=["mp4", "gif", "png"])
  assert sorted(p.rsplit("/", 1)[1] for p in files) == sorted(
      [f"orbit_{c}.{f}" for c in compositing.OUTPUTS for f in ("mp4", "gif")] + ["orbit_sheet.png"])
  even = (height + height % 2, width + width % 2)  # H.264 (yuv420p) needs even sizes: odd ones are padded
  for channel in compositing.OUTPUTS:
    reader = imageio.get_reader(str(tmp_path / "out" / f"orbit_{channel}.mp4"), format="FFMPEG")
    assert reader.get_meta_data()["fps"] == pytest.approx(12)
    mp4 = np.stack([image for image in reader.iter_data()])
    reader.close()
    assert mp4.shape == (num_frames,) + even + (3,), channel
    gif = np.asarray(imageio.mimread(str(tmp_path / "out" / f"orbit_{channel}.gif")))
    # (A gif stores a run of identical frames as one longer frame, as happens to the constant acc here.)
    assert gif.shape[:3] == (1 if channel == "acc" else num_frames, height, width), channel
  # The rgb video shows the archive's frames (up to compression).
  reader = imageio.get_reader(str(tmp_path / "out" / "orbit_rgb.mp4"), format="FFMPEG")
  for i, image in enumerate(reader.iter_data()):
    want = _frame(i, num_frames, height, width)["rgb"].astype(float)
    assert np.abs(image[:height, :width].astype(float) - want).mean() < 8, i
  reader.close()
  gif = np.asarray(imageio.mimread(str(tmp_path / "out" / "orbit_rgb.gif")))[..., :3]
  assert np.abs(gif[2].astype(float) - _frame(2, num_frames, height, width)["rgb"]).mean() < 8
  # Contact sheet: one row per channel, one column per (evenly spread) frame, 2-pixel gaps.
  sheet = imageio.imread(str(tmp_path / "out" / "orbit_sheet.png"))
  assert sheet.shape == (4 * height + 3 * 2, num_frames * width + (num_frames - 1) * 2, 3)
  np.testing.assert_array_equal(sheet[:height, :width], _frame(0, num_frames, height, width)["rgb"])


def test_export_finds_the_archive_in_a_workdir_and_defaults_to_its_folder(tmp_path):
  _archive(tmp_path / "renders" / "orbit.zarr", 3, 8, 8)
  files = export_tool.write_files(str(tmp_path), formats=["png"])
  assert files == [str(tmp_path / "renders" / "orbit_sheet.png")]
  assert not list((tmp_path / "renders").glob("*partial*"))


def test_missing_or_partial_archives_are_refused_naming_the_missing_frames(tmp_path, capsys):
  with pytest.raises(UserError, match="does not exist"):
    export_tool.write_files(str(tmp_path / "nowhere"))
  with pytest.raises(UserError, match="no orbit archive"):
    export_tool.write_files(str(tmp_path))
  _archive(tmp_path / "orbit.zarr", 5, 8, 8, frames=[0, 2, 4])
  with pytest.raises(SystemExit) as exit_info:
    export_tool.run(["video", f"--workdir={tmp_path / 'orbit.zarr'}"])
  assert exit_info.value.code == 2
  message = capsys.readouterr().err
  assert message.count("\n") == 1 and message.startswith("nerfpod: error: ")
  assert "incomplete: 2 of 5 frames are missing (1, 3)" in message and "--mode=render" in message
  assert not list(tmp_path.glob("orbit_*"))
  with pytest.raises(UserError, match="unknown export format"):
    export_tool.write_files(str(tmp_path / "orbit.zarr"), formats=["avi"])


# ---- pointcloud, mesh, cameras, depth: exports of a trained workdir ----------------------------------------

def _sdf(points_Nx3) -> np.ndarray:
  """Signed distance to the procedural scene's solids (scenes/procedural.py: sphere, box, cylinder, plate)."""
  p = np.asarray(points_Nx3, np.float64)

  def box(lo, hi):
    q = np.abs(p - (np.add(lo, hi) / 2)) - (np.subtract(hi, lo) / 2)
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0)

  def cylinder(xy, radius, z0, z1):
    d = np.stack([np.linalg.norm(p[:, :2] - xy, axis=1) - radius, np.abs(p[:, 2] - (z0 + z1) / 2) - (z1 - z0) / 2], 1)
    return np.minimum(d.max(1), 0) + np.linalg.norm(np.maximum(d, 0), axis=1)

  sphere = np.linalg.norm(p - [0.45, 0.35, 0.45], axis=1) - 0.45
  return np.min([sphere, box([-0.8, -0.7, 0.0], [-0.1, 0.0, 0.7]), cylinder([0.45, -0.55], 0.28, 0.0, 0.9),
                 cylinder([0.0, 0.0], 1.2, -0.08, 0.0)], axis=0)


def _read_ply(path) -> dict:
  """A binary little-endian PLY's elements as NumPy structured arrays (our own reader: header, then data)."""
  data = open(path, "rb").read()
  head, body = data.split(b"end_header\n", 1)
  lines = head.decode("ascii").splitlines()
  assert lines[:2] == ["ply", "format binary_little_endian 1.0"], lines[:2]
  types = {"float": "<f4", "uchar": "u1", "int": "<i4"}
  elements, out = [], {}
  for line in lines[2:]:
    words = line.split()
    if words[0] == "element":
      elements.append((words[1], int(words[2]), []))
    elif words[0] == "property" and words[1] == "list":
      elements[-1][2].append(("n", "u1"))
      elements[-1][2].append((words[4], types[words[3]], (3,)))
    elif words[0] == "property":
      elements[-1][2].append((words[2], types[words[1]]))
  offset = 0
  for name, count, fields in elements:
    dtype = np.dtype(fields)
    out[name] = np.frombuffer(body, dtype, count, offset)
    offset += dtype.itemsize * count
  assert offset == len(body)
  return out


def _export(*argv):
  """nerfpod export ARGV in this process (JAX already runs: the 8 simulated devices)."""
  args = export_tool.parse_args([str(a) for a in argv])
  return export_tool.export(args)


@pytest.fixture(scope="module")
def smoke_workdir(smoke_run):
  """The session's smoke run (conftest.smoke_run), which the exports only read."""
  return smoke_run.workdir


def test_each_kind_refuses_bad_input_in_one_sentence(smoke_workdir, tmp_path, capsys):
  cases = [
      (["nope", "--workdir", smoke_workdir], "unknown kind 'nope'; choose one of video, pointcloud, mesh"),
      (["mesh", f"--workdir={tmp_path / 'missing'}"], "missing does not exist; check the --workdir path"),
      (["mesh", f"--workdir={tmp_path}"], "holds no config.json"),
      (["pointcloud", f"--workdir={smoke_workdir}", "--num_points=0"], "--num_points=0 must be at least 1"),
      (["mesh", f"--workdir={smoke_workdir}", f"--out={tmp_path / 'm.stl'}"], "must end in .ply or .obj"),
      (["depth", f"--workdir={smoke_workdir}", "--format=exr"], "--format=exr is not one of png, npy"),
      (["cameras", f"--workdir={smoke_workdir}", f"--out={tmp_path / 'a_file' / 'transforms.json'}"],
       "cannot be written"),
  ]
  (tmp_path / "a_file").write_text("not a folder")
  no_checkpoint = tmp_path / "untrained"
  no_checkpoint.mkdir()
  (no_checkpoint / "config.json").write_text((smoke_workdir / "config.json").read_text())
  cases.append((["depth", f"--workdir={no_checkpoint}"], "holds no checkpoint yet"))
  for argv, message in cases:
    with pytest.raises(SystemExit) as exit_info:
      export_tool.run([str(a) for a in argv])
    assert exit_info.value.code == 2, argv
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("nerfpod: error: ") and message in err, (argv, err)
  assert not (no_checkpoint / "exports").exists()


def test_cameras_round_trip_through_the_nerfstudio_loader_to_the_same_rays(smoke_workdir, tmp_path):
  """With a capture -> scene similarity in scene.json, the exported poses are the capture's: loaded back by
  nerfpod's nerfstudio loader (which normalises them its own way) they give the same rays, mapped back to
  the capture's frame, and the same pixels."""
  import json
  import shutil
  from conftest import smoke_config
  from nerfpod import scenes
  from nerfpod.nerf import poses as pose_math
  workdir = tmp_path / "run"
  shutil.copytree(smoke_workdir, workdir)
  angle = 0.7
  rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
  capture_to_scene = pose_math.similarity(0.25, rotation, [3.0, -1.0, 2.0])
  scene_json = json.loads((workdir / "scene.json").read_text())
  scene_json["capture_to_scene"] = capture_to_scene.tolist()
  (workdir / "scene.json").write_text(json.dumps(scene_json))
  out = tmp_path / "cams" / "transforms.json"
  _export("cameras", f"--workdir={workdir}", f"--out={out}")
  meta = json.loads(out.read_text())
  assert meta["camera_model"] == "PINHOLE" and len(meta["train_filenames"]) == 100
  original = scenes.load(smoke_config().data)
  loaded = scenes.load(smoke_config(**{"data.kind": "nerfstudio", "data.path": str(out.parent)}).data)

  def in_capture_frame(split, i, capture_to_scene):
    origins, directions = cameras.image_rays(split.poses[i], split.cameras[i])
    inverse = np.linalg.inv(capture_to_scene)
    directions = directions @ inverse[:3, :3].T
    return origins @ inverse[:3, :3].T + inverse[:3, 3], directions / np.linalg.norm(directions, axis=-1, keepdims=True)

  for name in ("train", "val", "test"):
    a, b = original.split(name), loaded.split(name)
    assert len(a) == len(b)
    for i in (0, len(a) - 1):
      np.testing.assert_array_equal(a.image_uint8(i), b.image_uint8(i))
      # The original through the inverse of scene.json's similarity, the loaded through its loader's own.
      want, got = in_capture_frame(a, i, capture_to_scene), in_capture_frame(b, i, np.asarray(loaded.transform))
      np.testing.assert_allclose(got[0], want[0], atol=2e-4)
      np.testing.assert_allclose(got[1], want[1], atol=2e-5)


def test_points_mesh_and_depth_in_the_captures_frame_are_the_normalized_ones_through_the_inverse_similarity(
    smoke_workdir, tmp_path):
  """With a capture -> scene similarity T(X) = s R (X - c) in scene.json (s != 1, a rotation, a translation), the
  point cloud's points and normals, the mesh's vertices and normals, and the depth maps (with their poses)
  written in the capture's frame are the --normalized export's through T's inverse, computed here in closed
  form: X = R^T Y / s + c, normals R^T n, depths / s."""
  import json
  import re
  import shutil
  from nerfpod.nerf import poses as pose_math
  workdir = tmp_path / "run"
  shutil.copytree(smoke_workdir, workdir)
  scale, angle, center = 0.25, 0.7, np.array([3.0, -1.0, 2.0])
  rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
  scene_json = json.loads((workdir / "scene.json").read_text())
  scene_json["capture_to_scene"] = pose_math.similarity(scale, rotation, center).tolist()
  (workdir / "scene.json").write_text(json.dumps(scene_json))

  def to_capture(points):
    return np.asarray(points, np.float64) @ rotation / scale + center  # row-wise R^T y / s + c

  def xyz(vertex, names="xyz"):
    return np.stack([vertex[n] for n in names], 1).astype(np.float64)

  def both(kind, *flags):
    """The export in the capture's frame and --normalized, each read back."""
    got = {}
    for name, extra in (("capture", ()), ("normalized", ("--normalized",))):
      out = tmp_path / f"{kind}_{name}{'' if kind == 'depth' else '.ply'}"
      _export(kind, f"--workdir={workdir}", f"--out={out}", *flags, *extra)
      got[name] = out if kind == "depth" else _read_ply(out)
    return got["capture"], got["normalized"]

  capture, normalized = both("pointcloud", "--num_points=200", "--min_opacity=0.05")
  a, b = capture["vertex"], normalized["vertex"]
  assert len(a) == len(b) > 0
  assert np.abs(to_capture(xyz(b)) - xyz(b)).max() > 1  # a far-off frame: the comparison below can tell
  np.testing.assert_allclose(xyz(a), to_capture(xyz(b)), rtol=1e-5, atol=1e-5)
  np.testing.assert_allclose(xyz(a, ("nx", "ny", "nz")), xyz(b, ("nx", "ny", "nz")) @ rotation, atol=1e-5)
  np.testing.assert_array_equal(xyz(a, ("red", "green", "blue")), xyz(b, ("red", "green", "blue")))

  with pytest.raises(UserError, match=r"spans (\S+) to (\S+)\)") as refused:  # the 20-step density's range
    _export("mesh", f"--workdir={workdir}", f"--out={tmp_path / 'none.ply'}", "--resolution=16", "--level=1e9")
  low, high = map(float, re.search(r"spans (\S+) to (\S+)\)", str(refused.value)).groups())
  capture, normalized = both("mesh", "--resolution=16", f"--level={(low + high) / 2}")
  a, b = capture["vertex"], normalized["vertex"]
  assert len(a) == len(b) > 0
  np.testing.assert_array_equal(capture["face"]["vertex_indices"], normalized["face"]["vertex_indices"])
  np.testing.assert_allclose(xyz(a), to_capture(xyz(b)), rtol=1e-5, atol=1e-5)
  np.testing.assert_allclose(xyz(a, ("nx", "ny", "nz")), xyz(b, ("nx", "ny", "nz")) @ rotation, atol=1e-5)

  capture, normalized = both("depth", "--split=test", "--format=npy", "--min_opacity=0.1")
  views = [json.loads((folder / "depth.json").read_text())["views"] for folder in (capture, normalized)]
  for a, b in list(zip(*views))[:2]:
    depth_a, depth_b = np.load(capture / a["file"]), np.load(normalized / b["file"])
    assert (depth_b > 0).any()
    np.testing.assert_allclose(depth_a, depth_b / scale, rtol=1e-5)
    pose_a, pose_b = np.asarray(a["transform_matrix"]), np.asarray(b["transform_matrix"])
    np.testing.assert_allclose(pose_a[:3, 3], to_capture(pose_b[None, :3, 3])[0], atol=1e-9)
    np.testing.assert_allclose(pose_a[:3, :3], rotation.T @ pose_b[:3, :3], atol=1e-9)


def test_a_pose_refined_run_exports_its_training_frames_corrected_poses(smoke_workdir, tmp_path):
  """Training frames: the corrected pose (in the capture's frame) and the given one beside it; held-out frames:
  their given poses."""
  import dataclasses
  import json
  from nerfpod.export import cameras as cameras_export
  from nerfpod.nerf import pose_correction
  from nerfpod.run import trained as run_trained
  trained = run_trained.restore(str(smoke_workdir))
  train = trained.comps.scene.split("train")
  corrections = np.random.default_rng(0).uniform(-0.05, 0.05, (len(train), 6)).astype(np.float32)
  params = {"params": {**trained.params["params"], pose_correction.PARAM: corrections}}
  refined = dataclasses.replace(trained, params=params, capture_to_scene=np.diag([0.5, 0.5, 0.5, 1.0]))
  out = tmp_path / "transforms.json"
  cameras_export.export(types.SimpleNamespace(normalized=False), refined, str(out))
  meta = json.loads(out.read_text())
  assert meta["nerfpod"]["pose_refined"] is True
  frames = {f["file_path"]: f for f in meta["frames"]}
  want = pose_correction.corrected_poses(train.poses, corrections)
  want[:, :3, 3] *= 2.0  # scene -> capture: the inverse of the similarity's scale 0.5
  given = np.asarray(train.poses, np.float64).copy()
  given[:, :3, 3] *= 2.0
  for i in (0, len(train) - 1):
    frame = frames[f"images/train_{i:04d}.png"]
    np.testing.assert_allclose(frame["transform_matrix"], want[i], atol=1e-9)
    np.testing.assert_allclose(frame["nerfpod_given_transform_matrix"], given[i], atol=1e-9)
  test = trained.comps.scene.split("test")
  frame = frames["images/test_0000.png"]
  assert "nerfpod_given_transform_matrix" not in frame
  np.testing.assert_allclose(np.asarray(frame["transform_matrix"])[:3, :3], test.poses[0][:3, :3], atol=1e-6)


def test_depth_maps_read_back_as_the_rendered_depth(smoke_workdir, tmp_path):
  import json
  from PIL import Image
  from nerfpod.export import shared
  from nerfpod.run import trained as run_trained
  out_png, out_npy = tmp_path / "png", tmp_path / "npy"
  _export("depth", f"--workdir={smoke_workdir}", "--split=test", f"--out={out_png}", "--min_opacity=0.1")
  _export("depth", f"--workdir={smoke_workdir}", "--split=test", f"--out={out_npy}", "--format=npy",
          "--min_opacity=0.1")
  meta = json.loads((out_png / "depth.json").read_text())
  assert len(meta["views"]) == 8 and meta["coordinates"] == "capture"
  trained = run_trained.restore(str(smoke_workdir))
  split = trained.comps.scene.split("test")
  for view in meta["views"][:2]:
    png = np.asarray(Image.open(out_png / view["file"]))
    assert png.dtype == np.uint16 and png.shape == (32, 32) and png.max() == 65535
    npy = np.load(out_npy / view["file"].replace(".png", ".npy"))
    np.testing.assert_allclose(png * view["scale"], npy, atol=view["scale"])
    # Against the renderer: rays' expected depth (over their opacity) is the z-depth (camera z of a
    # direction is -1), 0 where the opacity is under 0.1.
    i = view["index"]
    origins, directions = cameras.image_rays(split.poses[i], split.cameras[i])
    out = shared.render_rays(trained, origins.reshape(-1, 3), directions.reshape(-1, 3), 1024)
    want = np.where(out["acc"] >= 0.1, out["depth"] / np.maximum(out["acc"], 1e-10), 0).reshape(32, 32)
    np.testing.assert_allclose(npy, want, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(view["transform_matrix"], split.poses[i], atol=1e-6)


def test_pointcloud_and_mesh_files_read_back(smoke_workdir, tmp_path):
  trimesh = pytest.importorskip("trimesh")
  cloud = tmp_path / "cloud.ply"
  _export("pointcloud", f"--workdir={smoke_workdir}", f"--out={cloud}", "--num_points=500", "--min_opacity=0.05")
  data = _read_ply(cloud)["vertex"]
  assert 0 < len(data) <= 500 and set(data.dtype.names) == {"x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"}
  normals = np.stack([data["nx"], data["ny"], data["nz"]], 1)
  np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-4)
  points = trimesh.load(cloud)
  np.testing.assert_allclose(points.vertices, np.stack([data["x"], data["y"], data["z"]], 1), rtol=1e-6)
  assert (np.abs(points.vertices) <= 1.5 + 1e-6).all()  # the hash grid's box
  # The 20-step model's density is nearly flat: a level outside it is refused, naming its range.
  with pytest.raises(UserError, match=r"the density never crosses --level=1000 in the box \[-1.5, 1.5\]\^3 \(it "
                                      r"spans (\S+) to (\S+)\); pass a --level in that range") as refused:
    _export("mesh", f"--workdir={smoke_workdir}", f"--out={tmp_path / 'none.ply'}", "--resolution=24", "--level=1000")
  import re
  low, high = map(float, re.search(r"spans (\S+) to (\S+)\)", str(refused.value)).groups())
  for suffix in ("ply", "obj"):
    path = tmp_path / f"mesh.{suffix}"
    _export("mesh", f"--workdir={smoke_workdir}", f"--out={path}", "--resolution=24", f"--level={(low + high) / 2}")
    mesh = trimesh.load(path, process=False)
    assert len(mesh.faces) > 0 and mesh.vertices.shape[1] == 3 and (np.abs(mesh.vertices) <= 1.5 + 1e-6).all()
    assert mesh.visual.vertex_colors.shape == (len(mesh.vertices), 4)


@pytest.mark.slow
def test_mesh_and_point_cloud_lie_on_the_procedural_scenes_true_surfaces(default_run, tmp_path):
  """The main job's model (conftest.default_run, also the README's headline metrics); the scene's solids span
  2.4 units: the median distance to the true surfaces is within 1.5% of that for the point cloud, 2% for the
  mesh. Most of the mesh lies on the solids' surfaces; the rest is the density inside them and under the
  plate, which no camera sees (never trained)."""
  assert default_run.result.returncode == 0, default_run.result.stderr[-3000:]
  run = default_run.workdir
  cloud, mesh = tmp_path / "cloud.ply", tmp_path / "mesh.ply"
  _export("pointcloud", f"--workdir={run}", f"--out={cloud}", "--num_points=20000")
  _export("mesh", f"--workdir={run}", f"--out={mesh}", "--resolution=96")
  vertex = _read_ply(cloud)["vertex"]
  points = np.stack([vertex["x"], vertex["y"], vertex["z"]], 1)
  normals = np.stack([vertex["nx"], vertex["ny"], vertex["nz"]], 1)
  distance = np.abs(_sdf(points))
  print(f"point cloud: median distance {np.median(distance):.4f}, within 0.05: {np.mean(distance < 0.05):.3f}")
  assert len(points) == 20000 and np.median(distance) < 0.036 and np.mean(distance < 0.05) > 0.7, \
      (np.median(distance), np.mean(distance < 0.05))
  eps = 1e-3  # the true outward normals: the signed distance's gradient
  true_normals = np.stack([(_sdf(points + eps * e) - _sdf(points - eps * e)) / (2 * eps) for e in np.eye(3)], 1)
  print(f"point cloud: normals on the true side: {np.mean(np.sum(normals * true_normals, 1) > 0):.3f}")
  assert np.mean(np.sum(normals * true_normals, 1) > 0) > 0.8
  faces = _read_ply(mesh)
  vertices = np.stack([faces["vertex"][k] for k in "xyz"], 1).astype(np.float64)
  triangles = vertices[faces["face"]["vertex_indices"]]
  rng = np.random.default_rng(0)  # points spread evenly over the mesh's area
  area = 0.5 * np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=1)
  chosen = rng.choice(len(triangles), 20000, p=area / area.sum())
  u, v = rng.uniform(size=(2, 20000, 1))
  flip = (u + v) > 1
  u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
  t = triangles[chosen]
  samples = t[:, 0] + u * (t[:, 1] - t[:, 0]) + v * (t[:, 2] - t[:, 0])
  distance = np.abs(_sdf(samples))
  print(f"mesh: {len(vertices)} vertices; median distance {np.median(distance):.4f}, within 0.05: "
        f"{np.mean(distance < 0.05):.3f}")
  assert np.median(distance) < 0.048 and np.mean(distance < 0.05) > 0.5, (np.median(distance), np.mean(distance < 0.05))
  # Every visible solid is there: points on the sphere's upper half lie near the mesh's vertices.
  from scipy.spatial import cKDTree
  up = rng.normal(size=(2000, 3))
  up = up[up[:, 2] > 0.2] / np.linalg.norm(up[up[:, 2] > 0.2], axis=1, keepdims=True)
  gaps, _ = cKDTree(vertices).query(np.array([0.45, 0.35, 0.45]) + 0.45 * up)
  print(f"mesh: median gap from the sphere's upper half to a vertex {np.median(gaps):.4f}")
  assert np.median(gaps) < 0.04, np.median(gaps)


def test_a_workdir_whose_every_checkpoint_is_damaged_is_one_sentence_and_nothing_after_it(smoke_workdir, tmp_path):
  """The command on a workdir none of whose checkpoints reads back whole: exit 2, one sentence naming each step,
  and none of the reports of the reads orbax abandoned when the restore failed (a traceback per array). In a
  process of its own: some of those reports come only as the interpreter exits (unfinished coroutines)."""
  import shutil
  import subprocess
  import sys
  from conftest import ABANDONED_READ_REPORTS, REPO, damage_checkpoint
  from procs import environment
  workdir = tmp_path / "damaged"
  shutil.copytree(smoke_workdir, workdir)
  steps = sorted(p for p in (workdir / "checkpoints").iterdir() if p.name.isdigit())
  for step in steps:
    damage_checkpoint(step)
  done = subprocess.run([sys.executable, "-m", "nerfpod.export", "pointcloud", f"--workdir={workdir}",
                         "--num_points=100"], cwd=REPO, env=environment(1), capture_output=True, text=True,
                        timeout=300)
  assert done.returncode == 2, done.stderr[-3000:]
  (error,) = [line for line in done.stderr.splitlines() if "error:" in line]
  assert error.startswith(f"nerfpod: error: no checkpoint in {workdir / 'checkpoints'} reads back whole")
  assert all(f"step {step.name}: " in error for step in steps), error
  for noise in ABANDONED_READ_REPORTS:
    assert noise not in done.stderr, done.stderr[-3000:]


def test_the_command_line_exports_and_prints_its_progress(smoke_workdir, tmp_path, capsys, monkeypatch):
  """`nerfpod export KIND ...` as the console script runs it, in a process of its own (one CPU device: the command
  starts JAX itself and restores the run saved from 8); each kind's --help, in this process (one of them through
  the console script's function, nerfpod.cli.run: a process each costs two seconds of imports)."""
  import os
  import subprocess
  import sys
  from nerfpod import cli
  import procs
  from conftest import REPO
  env = dict(os.environ, JAX_PLATFORMS="cpu")
  done = subprocess.run([sys.executable, "-c", "from nerfpod import cli; cli.run()", "export", "pointcloud",
                         f"--workdir={smoke_workdir}", f"--out={tmp_path / 'cloud.ply'}", "--num_points=100",
                         "--min_opacity=0.05"], cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
  assert done.returncode == 0, done.stderr[-2000:]
  assert "nerfpod: restored step 20 of" in done.stdout and "pointcloud 100/100 points" in done.stdout
  assert len(_read_ply(tmp_path / "cloud.ply")["vertex"]) == 100
  done = procs.in_process(cli.run, "nerfpod", capsys, monkeypatch, REPO)("export", "mesh", "--help")
  # absl's help spells a yes/no flag --[no]NAME
  assert done.returncode == 0 and "--[no]normalized" in done.stdout and "--resolution" in done.stdout, done.stderr
  for kind, own in (("pointcloud", "--num_points"), ("mesh", "--resolution"), ("cameras", "--workdir"),
                    ("depth", "--split")):
    with pytest.raises(SystemExit) as done:
      export_tool.run([kind, "--help"])
    out = capsys.readouterr().out
    assert done.value.code == 0 and "--[no]normalized" in out and "--workdir" in out and own in out, out


def test_a_mesh_resolution_that_cannot_fit_in_memory_is_refused_before_any_work(smoke_workdir, tmp_path, capsys,
                                                                                 monkeypatch):
  """--resolution is weighed against this host's available memory before anything is restored or written: a
  grid that cannot fit is one sentence (exit code 2) naming the memory it would take and the largest that fits;
  one that fits exports as before, saying its progress."""
  from nerfpod import text
  from nerfpod.export import mesh
  monkeypatch.setattr(mesh, "available_memory_bytes", lambda: 16 * 2 ** 20)  # 16 MiB
  fits = mesh.largest_resolution(mesh.MEMORY_SHARE * 16 * 2 ** 20)
  assert 8 <= fits < 96 and mesh.memory_bytes(fits) <= 12 * 2 ** 20 < mesh.memory_bytes(fits + 1)
  out = tmp_path / "exports" / "mesh.ply"
  with pytest.raises(SystemExit) as refused:
    export_tool.run(["mesh", f"--workdir={smoke_workdir}", f"--out={out}", "--resolution=96"])
  assert refused.value.code == 2
  captured = capsys.readouterr()
  assert (f"nerfpod: error: --resolution=96 would take about {text.byte_size(mesh.memory_bytes(96))} of memory (its 96^3 "
          f"density grid and marching cubes' working memory) but this host has 16.0 MiB available; pass "
          f"--resolution={fits} or less.") in captured.err, captured.err
  assert "restored" not in captured.out and not (tmp_path / "exports").exists()  # nothing restored or made
  # A resolution that fits: the density pass reports its progress, and the export is written as before.
  with pytest.raises(UserError, match=r"spans (\S+) to (\S+)\)") as level:
    _export("mesh", f"--workdir={smoke_workdir}", f"--out={out}", "--resolution=24", "--level=1000")
  import re
  low, high = map(float, re.search(r"spans (\S+) to (\S+)\)", str(level.value)).groups())
  _export("mesh", f"--workdir={smoke_workdir}", f"--out={out}", "--resolution=24", f"--level={(low + high) / 2}")
  assert "nerfpod: export: mesh: density 24/24 planes" in capsys.readouterr().out
  assert len(_read_ply(out)["face"]) > 0


def test_a_long_mesh_export_says_its_time_and_memory_up_front(smoke_workdir, tmp_path, capsys, monkeypatch):
  """Field queries a second are measured before the density pass; an export expected to take longer than
  SAY_ESTIMATE_SECONDS says how long and how much memory before it starts."""
  import re
  from nerfpod.export import mesh
  monkeypatch.setattr(mesh, "SAY_ESTIMATE_SECONDS", 0.0)  # every export counts as long
  with pytest.raises(UserError, match="the density never crosses --level=1000"):
    _export("mesh", f"--workdir={smoke_workdir}", f"--out={tmp_path / 'mesh.ply'}", "--resolution=96", "--level=1000")
  lines = capsys.readouterr().out.splitlines()
  (estimate,) = [i for i, line in enumerate(lines) if "mesh: a 96^3 grid (" in line]
  assert re.search(r"field queries at \S+ a second measured, then marching cubes\) takes about \S+ (ms|s|min \d+ s|h \d+ min) and "
                   r"[\d.,]+ [KMG]iB of memory", lines[estimate]), lines[estimate]
  (done,) = [i for i, line in enumerate(lines) if "mesh: density 96/96 planes" in line]
  assert estimate < done
