"""Exporting an orbit archive: colour maps, videos read back, the contact sheet, refusing partial archives."""
import imageio.v2 as imageio
import numpy as np
import pytest

from nerfpod import archive as archives
from nerfpod import orbit, video
from nerfpod.errors import UserError
from nerfpod.nerf import cameras, compositing
from nerfpod import export as export_tool

NEAR, FAR = 2.0, 6.0
# Reading an mp4 back starts ffmpeg as a child process, which JAX (imported by other tests) warns about.
pytestmark = pytest.mark.filterwarnings(r"ignore:os\.fork\(\) was called:RuntimeWarning")


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
  for run, argv in ((export_tool.run, ["video", f"--workdir={tmp_path / 'orbit.zarr'}"]),
                    (export_tool.run_video_alias, [str(tmp_path / "orbit.zarr")])):  # nerfpod-export's spelling
    with pytest.raises(SystemExit) as exit_info:
      run(argv)
    assert exit_info.value.code == 2
    message = capsys.readouterr().err
    assert message.count("\n") == 1 and message.startswith(("nerfpod export: error: ", "nerfpod-export: error: "))
    assert "incomplete: 2 of 5 frames are missing (1, 3)" in message and "--mode=render" in message
  assert not list(tmp_path.glob("orbit_*"))
  with pytest.raises(UserError, match="unknown export format"):
    export_tool.write_files(str(tmp_path / "orbit.zarr"), formats=["avi"])
