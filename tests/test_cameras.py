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


# Lens distortion: the fox capture's OpenCV parameters, and a strong barrel + tangential lens.
FOX_LENS = (0.0578421, -0.0805099, 0.0, 0.0, -0.000980296, 0.00015575)
STRONG_LENS = (-0.3, 0.12, -0.02, 0.0, 0.004, -0.003)


@pytest.mark.parametrize("lens", [FOX_LENS, STRONG_LENS])
def test_undistort_inverts_distort(lens):
  rng = np.random.default_rng(1)
  x, y = rng.uniform(-0.6, 0.6, (2, 1000))  # normalised coordinates: a 62-degree field of view
  xd, yd = cameras.distort(x, y, lens)
  assert np.abs(np.hypot(xd - x, yd - y)).max() > (1e-3 if lens == FOX_LENS else 3e-2)  # it does distort
  ux, uy = cameras.undistort(xd, yd, lens)
  np.testing.assert_allclose(ux, x, atol=1e-9)
  np.testing.assert_allclose(uy, y, atol=1e-9)


def test_distort_is_the_radial_tangential_formula():
  """Each coefficient alone against its textbook term (OpenCV's documentation)."""
  x, y = np.array([0.3, -0.2]), np.array([0.1, 0.4])
  r2 = x * x + y * y
  for i, name in enumerate(cameras.DISTORTION_PARAMS):
    lens = np.zeros(6)
    lens[i] = 0.1
    xd, yd = cameras.distort(x, y, lens)
    if name.startswith("k"):
      power = int(name[1])
      np.testing.assert_allclose(xd, x * (1 + 0.1 * r2**power))
      np.testing.assert_allclose(yd, y * (1 + 0.1 * r2**power))
    elif name == "p1":
      np.testing.assert_allclose(xd, x + 0.2 * x * y)
      np.testing.assert_allclose(yd, y + 0.1 * (r2 + 2 * y * y))
    else:
      np.testing.assert_allclose(xd, x + 0.1 * (r2 + 2 * x * x))
      np.testing.assert_allclose(yd, y + 0.2 * x * y)


@pytest.mark.parametrize("model,params", [
    ("SIMPLE_RADIAL", (70.0, 41.0, 29.5, -0.2)),
    ("RADIAL", (70.0, 41.0, 29.5, -0.2, 0.05)),
    ("OPENCV", (70.0, 75.0, 41.0, 29.5) + (FOX_LENS[0], FOX_LENS[1], FOX_LENS[4], FOX_LENS[5])),
    ("OPENCV", (70.0, 75.0, 41.0, 29.5, -0.3, 0.12, 0.004, -0.003)),
])
def test_rays_through_distorted_pixels_project_back_through_colmaps_own_model(model, params):
  """The ray of a pixel, projected by COLMAP's forward model (pycolmap's img_from_cam), lands on that pixel:
  per-ray Newton undistortion against the reference implementation of the lens."""
  pycolmap = pytest.importorskip("pycolmap")
  from nerfpod.scenes import colmap
  cam = pycolmap.Camera.create_from_model_name(1, model, 1.0, 80, 60)
  cam.params = list(params)
  p = colmap.camera_params(model, params, 80, 60, "test")
  intr = cameras.Intrinsics(80, 60, p["fx"], p["fy"], p["cx"], p["cy"],
                            tuple(p.get(k, 0.0) for k in cameras.DISTORTION_PARAMS))
  cams = cameras.Cameras.stack([intr])
  rows, cols = np.meshgrid(np.arange(60), np.arange(80), indexing="ij")
  pose = np.eye(4)
  _, directions = cameras.frame_rays(pose[None, None], cams, np.zeros_like(rows), rows, cols, 0.5)
  opencv = directions.reshape(-1, 3).astype(np.float64) * np.array([1.0, -1.0, -1.0])  # OpenGL -> OpenCV axes
  pixels = np.asarray(cam.img_from_cam(opencv))
  np.testing.assert_allclose(pixels[:, 0], cols.ravel() + 0.5, atol=1e-4)
  np.testing.assert_allclose(pixels[:, 1], rows.ravel() + 0.5, atol=1e-4)
  # nerfpod's own forward model (project) agrees with COLMAP's, and undistortion was needed.
  xy, _ = cameras.project(directions.reshape(-1, 3) * 3.0, pose, intr)
  np.testing.assert_allclose(xy, pixels, atol=1e-4)
  pinhole = cameras.Intrinsics(80, 60, intr.fx, intr.fy, intr.cx, intr.cy)
  assert np.abs(cameras.image_rays(pose, pinhole)[1].reshape(-1, 3) - directions.reshape(-1, 3)).max() > 1e-3


def test_cameras_hold_one_camera_per_frame():
  a = cameras.Intrinsics(40, 30, 50.0, 51.0, 20.0, 15.0)
  b = cameras.Intrinsics(20, 10, 25.0, 25.0, 10.5, 4.5, STRONG_LENS)
  cams = cameras.Cameras.stack([a, b, a])
  assert len(cams) == 3 and cams[0] == a and cams[1] == b and cams.is_distorted
  np.testing.assert_array_equal(cams.num_pixels, [1200, 200, 1200])
  assert cams.select([1])[0] == b and not cams.select([0, 2]).is_distorted


def test_viewer_cameras_and_nerfpod_poses_convert_both_ways():
  pose = cameras.look_at(np.array([1.0, -3.0, 2.0]))  # OpenGL: looks down -z at the origin, +y up
  wxyz, position = cameras.pose_to_opencv(pose)
  np.testing.assert_allclose(cameras.pose_from_opencv(wxyz, position), pose, atol=1e-12)
  # viser's camera (OpenCV) looks down its +z and has +y down: the same direction and the opposite up.
  tf = pytest.importorskip("viser.transforms", reason="viser (the viewer extra) is absent")
  rotation = tf.SO3(wxyz).as_matrix()
  np.testing.assert_allclose(rotation[:, 2], -pose[:3, 2], atol=1e-12)
  np.testing.assert_allclose(rotation[:, 1], -pose[:3, 1], atol=1e-12)
  np.testing.assert_allclose(rotation[:, 2], -position / np.linalg.norm(position), atol=1e-12)


def test_a_camera_from_its_vertical_field_of_view_and_back():
  intr = cameras.intrinsics_from_fov(np.radians(90.0), 40, 20)  # tan(45 deg) = 1: focal = half the height
  assert (intr.fx, intr.fy, intr.cx, intr.cy) == pytest.approx((10.0, 10.0, 20.0, 10.0))
  assert cameras.fov_y(intr) == pytest.approx(np.radians(90.0))


def test_quaternions_and_rotations_convert_both_ways():
  rng = np.random.default_rng(0)
  for _ in range(20):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    rotation = cameras.quaternion_to_rotation(q)
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(cameras.rotation_to_quaternion(rotation), q if q[0] >= 0 else -q, atol=1e-12)
