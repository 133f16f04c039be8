"""Camera paths drawn from a capture's cameras (nerf/paths.py): the LLFF spiral against a verbatim port of
the original code (on synthetic poses and on the real horns capture), mip-NeRF 360's ellipse against a port
of multinerf's, and what both must be: cameras that look at the scene, upright, evenly paced."""
import numpy as np
import pytest

from conftest import DATA, require
from nerfpod.nerf import cameras, paths, poses as pose_math


# --- bmild/nerf load_llff.py, verbatim but for the hwf column, which nerfpod keeps apart ---------------------
def normalize(x):
  return x / np.linalg.norm(x)


def viewmatrix(z, up, pos):
  vec2 = normalize(z)
  vec1_avg = up
  vec0 = normalize(np.cross(vec1_avg, vec2))
  vec1 = normalize(np.cross(vec2, vec0))
  m = np.stack([vec0, vec1, vec2, pos], 1)
  return m


def poses_avg(poses):
  center = poses[:, :3, 3].mean(0)
  vec2 = normalize(poses[:, :3, 2].sum(0))
  up = poses[:, :3, 1].sum(0)
  c2w = viewmatrix(vec2, up, center)
  return c2w


def render_path_spiral(c2w, up, rads, focal, zdelta, zrate, rots, N):
  render_poses = []
  rads = np.array(list(rads) + [1.])
  for theta in np.linspace(0., 2. * np.pi * rots, N + 1)[:-1]:
    c = np.dot(c2w[:3, :4], np.array([np.cos(theta), -np.sin(theta), -np.sin(theta * zrate), 1.]) * rads)
    z = normalize(c - np.dot(c2w[:3, :4], np.array([0, 0, -focal, 1.])))
    render_poses.append(viewmatrix(z, up, c))
  return render_poses


def recenter_poses(poses):
  poses_ = poses + 0
  bottom = np.reshape([0, 0, 0, 1.], [1, 4])
  c2w = poses_avg(poses)
  c2w = np.concatenate([c2w[:3, :4], bottom], -2)
  bottom = np.tile(np.reshape(bottom, [1, 1, 4]), [poses.shape[0], 1, 1])
  poses = np.concatenate([poses[:, :3, :4], bottom], -2)
  poses = np.linalg.inv(c2w) @ poses
  poses_[:, :3, :4] = poses[:, :3, :4]
  poses = poses_
  return poses


def load_llff_spiral(poses, bds):
  """load_llff_data's spiral branch (bd_factor .75, recenter, not spherify, not path_zflat)."""
  sc = 1. / (bds.min() * .75)
  poses[:, :3, 3] *= sc
  bds *= sc
  poses = recenter_poses(poses)
  c2w = poses_avg(poses)
  up = normalize(poses[:, :3, 1].sum(0))
  close_depth, inf_depth = bds.min() * .9, bds.max() * 5.
  dt = .75
  mean_dz = 1. / (((1. - dt) / close_depth + dt / inf_depth))
  focal = mean_dz
  zdelta = close_depth * .2
  tt = poses[:, :3, 3]
  rads = np.percentile(np.abs(tt), 90, 0)
  c2w_path = c2w
  N_views = 120
  N_rots = 2
  render_poses = render_path_spiral(c2w_path, up, rads, focal, zdelta, zrate=.5, rots=N_rots, N=N_views)
  return poses, bds, np.array(render_poses).astype(np.float32)
# -------------------------------------------------------------------------------------------------------------


def _forward_facing(n=20, seed=0):
  """Cameras of a forward-facing capture (OpenGL, looking roughly down -z) and depth bounds."""
  rng = np.random.default_rng(seed)
  poses = np.stack([cameras.look_at(np.array([*rng.uniform(-1, 1, 2), 0.0]) + rng.normal(0, 0.05, 3),
                                    target=(rng.normal(0, 0.3), rng.normal(0, 0.3), -10.0), up=(0, 1, 0))
                    for _ in range(n)])
  bds = np.stack([rng.uniform(8, 9, n), rng.uniform(40, 60, n)], -1)
  return poses, bds


def _as_llff(poses):
  """nerfpod's 4x4 OpenGL poses -> load_llff's (N, 3, 5) after its axis fix ([right, up, back]; hwf zero)."""
  return np.concatenate([poses[:, :3, :4], np.zeros((len(poses), 3, 1))], -1)


def test_spiral_equals_the_original_render_path_spiral():
  poses, bds = _forward_facing()
  ref_poses, ref_bds, want = load_llff_spiral(_as_llff(poses), bds.copy())
  ref_4x4 = np.concatenate([ref_poses[:, :3, :4], np.tile([[[0, 0, 0, 1.0]]], (len(poses), 1, 1))], 1)
  got = paths.spiral(ref_4x4, ref_bds.min(), ref_bds.max())
  assert got.shape == (120, 4, 4)
  np.testing.assert_allclose(got[:, :3, :4], want, atol=1e-6)
  np.testing.assert_array_equal(got[:, 3], np.tile([0, 0, 0, 1.0], (120, 1)))


def test_spiral_on_the_real_horns_capture_equals_the_original():
  """The shared LLFF horns capture, loaded as load_llff_data does (axis fix, bounds rescale, recentring)."""
  raw = np.load(require(DATA / "llff_horns" / "poses_bounds.npy"))
  poses = raw[:, :-2].reshape([-1, 3, 5])
  bds = raw[:, -2:].copy()
  poses = np.concatenate([poses[:, :, 1:2], -poses[:, :, 0:1], poses[:, :, 2:]], 2)
  ref_poses, ref_bds, want = load_llff_spiral(poses, bds)
  ref_4x4 = np.concatenate([ref_poses[:, :3, :4], np.tile([[[0, 0, 0, 1.0]]], (len(ref_poses), 1, 1))], 1)
  got = paths.spiral(ref_4x4, ref_bds.min(), ref_bds.max())
  np.testing.assert_allclose(got[:, :3, :4], want, atol=1e-5)


def test_spiral_cameras_look_at_the_focus_point_and_turn_twice():
  poses, bds = _forward_facing()
  near, far = bds.min(), bds.max()
  got = paths.spiral(poses, near, far, num_frames=40)
  average = pose_math.poses_avg(poses)
  focus = 1.0 / (0.25 / (0.9 * near) + 0.75 / (5.0 * far))
  target = average[:3, :3] @ np.array([0, 0, -focus]) + average[:3, 3]
  intr = cameras.Intrinsics.from_focal(40, 30, 30.0)
  for pose in got:
    np.testing.assert_allclose(pose[:3, :3].T @ pose[:3, :3], np.eye(3), atol=1e-9)
    xy, depth = cameras.project(target[None], pose, intr)
    np.testing.assert_allclose(xy[0], [intr.cx, intr.cy], atol=1e-6)
    assert depth[0] > 0 and pose[:3, 1] @ average[:3, 1] > 0.9  # in front of it, upright
  # Two turns: the offset from the average camera winds twice around its view axis.
  offsets = (got[:, :3, 3] - average[:3, 3]) @ average[:3, :3]
  angles = np.unwrap(np.arctan2(offsets[:, 1], offsets[:, 0]))
  angles = np.unwrap(np.append(angles, angles[0]))  # the closed loop, back to the first frame
  assert abs(angles[-1] - angles[0]) == pytest.approx(4 * np.pi, rel=1e-9)


# --- multinerf camera_utils.generate_ellipse_path and stepfun.sample (deterministic), ported to NumPy -------
def focus_point_fn(poses):
  directions, origins = poses[:, :3, 2:3], poses[:, :3, 3:4]
  m = np.eye(3) - directions * np.transpose(directions, [0, 2, 1])
  mt_m = np.transpose(m, [0, 2, 1]) @ m
  focus_pt = np.linalg.inv(mt_m.mean(0)) @ (mt_m @ origins).mean(0)[:, 0]
  return focus_pt


def stepfun_sample(t, w_logits, num_samples):
  eps = np.finfo(np.float32).eps
  u = np.linspace(0, 1. - eps, num_samples)
  w = np.exp(w_logits - w_logits.max())
  w = w / w.sum()
  cw = np.concatenate([[0.], np.minimum(1, np.cumsum(w[:-1])), [1.]])
  return np.interp(u, cw, t)


def generate_ellipse_path(poses, n_frames=120, const_speed=True, z_variation=0., z_phase=0.):
  center = focus_point_fn(poses)
  offset = np.array([center[0], center[1], 0])
  sc = np.percentile(np.abs(poses[:, :3, 3] - offset), 90, axis=0)
  low = -sc + offset
  high = sc + offset
  z_low = np.percentile((poses[:, :3, 3]), 10, axis=0)
  z_high = np.percentile((poses[:, :3, 3]), 90, axis=0)

  def get_positions(theta):
    return np.stack([
        low[0] + (high - low)[0] * (np.cos(theta) * .5 + .5),
        low[1] + (high - low)[1] * (np.sin(theta) * .5 + .5),
        z_variation * (z_low[2] + (z_high - z_low)[2] * (np.cos(theta + 2 * np.pi * z_phase) * .5 + .5)),
    ], -1)

  theta = np.linspace(0, 2. * np.pi, n_frames + 1, endpoint=True)
  positions = get_positions(theta)
  if const_speed:
    lengths = np.linalg.norm(positions[1:] - positions[:-1], axis=-1)
    theta = stepfun_sample(theta, np.log(lengths), n_frames + 1)
    positions = get_positions(theta)
  positions = positions[:-1]
  avg_up = poses[:, :3, 1].mean(0)
  avg_up = avg_up / np.linalg.norm(avg_up)
  ind_up = np.argmax(np.abs(avg_up))
  up = np.eye(3)[ind_up] * np.sign(avg_up[ind_up])
  return np.stack([viewmatrix(p - center, up, p) for p in positions])
# -------------------------------------------------------------------------------------------------------------


def _ring(n=30, seed=1):
  """A 360-degree capture: cameras on an uneven ring above the z = 0 plane, looking at a point near 0."""
  rng = np.random.default_rng(seed)
  angles = np.sort(rng.uniform(0, 2 * np.pi, n))
  eyes = np.stack([1.6 * np.cos(angles), 1.0 * np.sin(angles), rng.uniform(0.2, 0.5, n)], -1)
  return np.stack([cameras.look_at(e, target=(0.1, -0.05, 0.0)) for e in eyes])


@pytest.mark.parametrize("z_variation", [0.0, 0.5])
def test_ellipse_equals_multinerfs(z_variation):
  """multinerf's frame is centred on the cameras' mean position: its path, there, is nerfpod's."""
  poses = _ring()
  got = paths.ellipse(poses, 60, z_variation=z_variation, z_phase=0.25)
  height = poses[:, 2, 3].mean()
  centred = poses.copy()
  centred[:, 2, 3] -= height
  want = generate_ellipse_path(centred, 60, z_variation=z_variation, z_phase=0.25)
  want[:, 2, 3] += height
  np.testing.assert_allclose(got[:, :3, :4], want, atol=1e-9)


def test_ellipse_looks_at_the_focus_point_upright_at_constant_speed():
  poses = _ring()
  got = paths.ellipse(poses, 90)
  np.testing.assert_allclose(pose_math.focus_point(poses), [0.1, -0.05, 0.0], atol=1e-6)  # every axis meets there
  intr = cameras.Intrinsics.from_focal(40, 30, 30.0)
  for pose in got:
    xy, depth = cameras.project(np.array([[0.1, -0.05, 0.0]]), pose, intr)
    np.testing.assert_allclose(xy[0], [intr.cx, intr.cy], atol=1e-6)
    assert depth[0] > 0 and pose[2, 1] > 0  # world +z is up in the image
  np.testing.assert_allclose(got[:, 2, 3], poses[:, 2, 3].mean(), atol=1e-12)  # at the cameras' height
  steps = np.linalg.norm(np.diff(np.concatenate([got[:, :3, 3], got[:1, :3, 3]]), axis=0), axis=-1)
  assert steps.std() / steps.mean() < 0.02
  # Through the spread of the cameras: the 90th percentile of their offsets in x and y.
  extent = np.abs(got[:, :2, 3] - [0.1, -0.05]).max(0)
  np.testing.assert_allclose(extent, np.percentile(np.abs(poses[:, :2, 3] - [0.1, -0.05]), 90, axis=0),
                             rtol=0.01)
