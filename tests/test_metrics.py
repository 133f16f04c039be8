import numpy as np
import pytest

from nerfpod.render import metrics


def test_psnr_closed_form():
  a = np.zeros((8, 8, 3))
  assert metrics.psnr(a + 0.1, a) == pytest.approx(20.0)
  assert metrics.psnr(a + 0.01, a) == pytest.approx(40.0)


def test_ssim_of_identical_images_is_one_and_of_a_constant_shift_closed_form():
  rng = np.random.default_rng(0)
  a = rng.uniform(0.2, 0.8, (32, 32, 3))
  assert metrics.ssim(a, a) == pytest.approx(1.0)
  # Constant images c and c + d: SSIM = (2 c (c + d) + C1) / (c^2 + (c + d)^2 + C1).
  c, d, c1 = 0.3, 0.2, 0.01**2
  expected = (2 * c * (c + d) + c1) / (c**2 + (c + d)**2 + c1)
  assert metrics.ssim(np.full((20, 20, 3), c), np.full((20, 20, 3), c + d)) == pytest.approx(expected)


def test_ssim_of_images_smaller_than_the_window_is_defined():
  a = np.random.default_rng(2).uniform(size=(6, 8, 3))
  assert metrics.ssim(a, a) == pytest.approx(1.0)
  b = np.clip(a + 0.2, 0, 1)
  # The 11-pixel window shrinks to the largest odd size that fits the 6 rows, 5 (not 3: another value).
  assert metrics.ssim(a, b) == metrics.ssim(a, b, filter_size=5) != metrics.ssim(a, b, filter_size=3)
  c, d, c1 = 0.3, 0.2, 0.01**2  # constant images: the closed form of the test above, whatever the window
  expected = (2 * c * (c + d) + c1) / (c**2 + (c + d)**2 + c1)
  assert metrics.ssim(np.full((6, 8, 3), c), np.full((6, 8, 3), c + d)) == pytest.approx(expected)


def test_ssim_matches_scikit_image():
  skimage_metrics = pytest.importorskip("skimage.metrics")
  rng = np.random.default_rng(1)
  a = rng.uniform(0, 1, (48, 40, 3))
  b = np.clip(a + 0.1 * rng.normal(size=a.shape), 0, 1)
  reference = skimage_metrics.structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
                                                    use_sample_covariance=False, data_range=1.0,
                                                    channel_axis=-1)
  assert metrics.ssim(a, b) == pytest.approx(reference, abs=1e-9)
