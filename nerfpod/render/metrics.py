"""Image-quality metrics on [0, 1] images (NumPy): PSNR and SSIM as NeRF papers compute them."""
import jax
import jax.numpy as jnp
import numpy as np


def mse_to_psnr(mse):
  """PSNR in dB of a mean squared error of [0, 1] images: NumPy in, NumPy out; JAX (also traced) in, JAX out."""
  return -10.0 * (jnp if isinstance(mse, jax.Array) else np).log10(mse)


def psnr(image, reference) -> float:
  return float(mse_to_psnr(np.mean((np.asarray(image, np.float64) - np.asarray(reference, np.float64))**2)))


def _gaussian_kernel(size: int, sigma: float) -> np.ndarray:
  x = np.arange(size, dtype=np.float64) - (size - 1) / 2.0
  k = np.exp(-0.5 * (x / sigma)**2)
  return k / k.sum()


def _filter_valid(image_HxWxC, kernel):
  """Separable 2-D filtering, 'valid' region only (no padding), per channel."""
  k = len(kernel)
  h, w = image_HxWxC.shape[:2]
  rows = sum(kernel[i] * image_HxWxC[i:h - k + 1 + i] for i in range(k))
  return sum(kernel[i] * rows[:, i:w - k + 1 + i] for i in range(k))


def ssim(image, reference, max_val: float = 1.0, filter_size: int = 11, filter_sigma: float = 1.5,
         k1: float = 0.01, k2: float = 0.03) -> float:
  """Structural similarity (Wang et al. 2004) as NeRF evaluations compute it.

  A Gaussian window of 11 pixels with sigma 1.5 over the region where it fits entirely ('valid'), the
  constants K1 = 0.01 and K2 = 0.03, averaged over pixels and colour channels. This equals
  skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
  data_range=1) on images larger than the window; on smaller ones the window shrinks to fit.
  """
  a = np.asarray(image, np.float64)
  b = np.asarray(reference, np.float64)
  if a.ndim == 2:
    a, b = a[..., None], b[..., None]
  # An image smaller than the window: shrink the window (odd, at most the image) rather than average nothing.
  filter_size = min(filter_size, (min(a.shape[:2]) - 1) // 2 * 2 + 1)
  kernel = _gaussian_kernel(filter_size, filter_sigma)
  mu_a, mu_b = _filter_valid(a, kernel), _filter_valid(b, kernel)
  var_a = _filter_valid(a * a, kernel) - mu_a**2
  var_b = _filter_valid(b * b, kernel) - mu_b**2
  cov = _filter_valid(a * b, kernel) - mu_a * mu_b
  c1, c2 = (k1 * max_val)**2, (k2 * max_val)**2
  numerator = (2 * mu_a * mu_b + c1) * (2 * cov + c2)
  denominator = (mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2)
  return float(np.mean(numerator / denominator))
