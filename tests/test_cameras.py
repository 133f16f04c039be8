import numpy as np
import pytest

from nerfpod.nerf import cameras


def _random_pose(rng):
  eye = rng.normal(size=3)
  eye = 4.0 * eye / np.linalg.norm(eye)
  return cameras.look_at(eye, target=rng.normal(size=3) * 0.2)


@pytest.mark.parametrize("pixel_center", [0.5, 0.0])
def test_point_projects_to_the_pixel_whose_ray_passes_through_it(pixel_center):
  rng = np.random.default_rng(0)
  intr = cameras.Intrinsics(width=80, height=60, fx=70.0, fy=75.0, cx=41.0, cy=29.5)
  for _ in range(5):
    pose = _random_pose(rng)
    rows, cols = rng.integers(0, 60, 20), rng.integers(0, 80, 20)
    origins, directions = cameras.rays_for_pixels(pose[None], intr, rows, cols, pixel_center)
    t = rng.uniform(1.0, 5.0, 20)[:, None]
    points = origins + t * directions
    xy, depth = cameras.project(points, pose, intr)
    np.testing.assert_allclose(xy[:, 0], cols + pixel_center, atol=1e-4)
    np.testing.assert_allclose(xy[:, 1], rows + pixel_center, atol=1e-4)
    np.testing.assert_allclose(depth, t[:, 0], rtol=1e-5)  # camera-space z of directions is -1
    np.testing.assert_array_equal(np.floor(xy[:, ::-1] - pixel_center + 0.5).astype(int),
                                  np.stack([rows, cols], 1))


def test_image_rays_centre_ray_is_the_optical_axis():
  intr = cameras.Intrinsics.from_focal(101, 101, 100.0)
  pose = cameras.look_at(np.array([0.0, -4.0, 0.0]))
  origins, directions = cameras.image_rays(pose, intr, pixel_center=0.5)
  assert origins.shape == directions.shape == (101, 101, 3)
  np.testing.assert_allclose(directions[50, 50], [0.0, 1.0, 0.0], atol=1e-6)  # towards the origin
  np.testing.assert_allclose(origins[0, 0], [0.0, -4.0, 0.0], atol=1e-6)
  assert directions[0, 50, 2] > 0 and directions[50, 0, 0] < 0  # top row looks up, left column left


def _tutorial_pose_spherical(theta, phi, radius):
  """Verbatim from the Tiny NeRF tutorial."""
  trans_t = lambda t: np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, t], [0, 0, 0, 1]], float)
  rot_phi = lambda phi: np.array([[1, 0, 0, 0], [0, np.cos(phi), -np.sin(phi), 0],
                                  [0, np.sin(phi), np.cos(phi), 0], [0, 0, 0, 1]], float)
  rot_theta = lambda th: np.array([[np.cos(th), 0, -np.sin(th), 0], [0, 1, 0, 0],
                                   [np.sin(th), 0, np.cos(th), 0], [0, 0, 0, 1]], float)
  c2w = trans_t(radius)
  c2w = rot_phi(phi / 180.0 * np.pi) @ c2w
  c2w = rot_theta(theta / 180.0 * np.pi) @ c2w
  return np.array([[-1, 0, 0, 0], [0, 0, 1, 0], [0, 1, 0, 0], [0, 0, 0, 1]]) @ c2w


@pytest.mark.parametrize("azimuth", [0.0, 37.0, 200.0])
def test_spherical_pose_is_the_tutorials_and_looks_at_the_origin(azimuth):
  pose = cameras.spherical_pose(azimuth, -30.0, 4.0)
  np.testing.assert_allclose(pose, _tutorial_pose_spherical(azimuth, -30.0, 4.0), atol=1e-12)
  eye = pose[:3, 3]
  np.testing.assert_allclose(np.linalg.norm(eye), 4.0)
  np.testing.assert_allclose(eye[2], 4.0 * np.sin(np.deg2rad(30.0)))  # -30: above the plane
  np.testing.assert_allclose(-pose[:3, 2], -eye / 4.0, atol=1e-12)  # looks down -z at the origin
  np.testing.assert_allclose(pose[:3, :3].T @ pose[:3, :3], np.eye(3), atol=1e-12)
