"""Multi-host start-up (jax.distributed), the device mesh, and host-local <-> global arrays."""
import functools
import os

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import AxisType, Mesh, NamedSharding, PartitionSpec as P

from nerfpod.errors import UserError

DATA_AXIS = "data"
SLICE_AXIS = "slice"  # multi-slice runs only: the mesh's major axis, one entry per slice (make_mesh)
REGION_AXIS = "region"  # model.regions > 1 only: the mesh's minor axis, one entry per region of space


def initialize(coordinator_address: str | None = None, num_processes: int | None = None,
               process_id: int | None = None, heartbeat_timeout_seconds: int = 100,
               shutdown_timeout_seconds: int = 300, initialization_timeout: int = 300) -> None:
  """Starts jax.distributed when this is one process of several; must run before any other JAX call.

  Flags win over the standard variables JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES, JAX_PROCESS_ID. With
  none of them: on a Cloud TPU VM, JAX finds its peers itself (in the VM's metadata); anywhere else this is
  a single process.

  The timeouts bound how long a process waits for the others: a process whose peer stopped sending
  heartbeats for `heartbeat_timeout_seconds` stops with an error (instead of hanging in a collective);
  at exit it waits at most `shutdown_timeout_seconds` for the others; at start-up at most
  `initialization_timeout` for all of them to connect.
  """
  coordinator_address = coordinator_address or os.environ.get("JAX_COORDINATOR_ADDRESS") or None
  try:
    if num_processes is None and os.environ.get("JAX_NUM_PROCESSES"):
      num_processes = int(os.environ["JAX_NUM_PROCESSES"])
    if process_id is None and os.environ.get("JAX_PROCESS_ID"):
      process_id = int(os.environ["JAX_PROCESS_ID"])
  except ValueError as e:
    raise UserError(f"JAX_NUM_PROCESSES and JAX_PROCESS_ID must be integers ({e}).") from None
  for name, value in (("heartbeat_timeout_seconds", heartbeat_timeout_seconds),
                      ("shutdown_timeout_seconds", shutdown_timeout_seconds),
                      ("initialization_timeout", initialization_timeout)):
    if value <= 0:
      raise UserError(f"--{name}={value} must be a positive number of seconds.")
  timeouts = dict(heartbeat_timeout_seconds=heartbeat_timeout_seconds,
                  shutdown_timeout_seconds=shutdown_timeout_seconds,
                  initialization_timeout=initialization_timeout)
  if coordinator_address or (num_processes or 1) > 1:
    if not coordinator_address or num_processes is None or process_id is None:
      raise UserError("a multi-process run needs all of --coordinator_address, --num_processes and "
                      "--process_id (or JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES, JAX_PROCESS_ID).")
    if not 0 <= process_id < num_processes:
      raise UserError(f"--process_id={process_id} is outside [0, {num_processes}).")
    jax.distributed.initialize(coordinator_address=coordinator_address, num_processes=num_processes,
                               process_id=process_id, **timeouts)
  elif _on_cloud_tpu_vm():
    jax.distributed.initialize(**timeouts)


def wait_for_all(name: str, timeout_s: float = 600.0) -> None:
  """Waits until every process reaches this point (the distributed runtime's barrier; no device work).

  Before the first collective of a program that each process compiled itself: on CPU, the collectives'
  set-up waits only 30 s for the slowest peer, which a loaded machine compiling at different speeds
  exceeds; this barrier waits up to `timeout_s`."""
  if jax.process_count() == 1:
    return
  from jax._src import distributed as jax_distributed  # the runtime's client: no public barrier in jax
  client = jax_distributed.global_state.client
  if client is not None:
    client.wait_at_barrier(name, timeout_in_ms=int(timeout_s * 1000))


def pjrt_plugins() -> set[str]:
  """The PJRT plugins JAX will load when its backends start (e.g. 'xla_cuda13' from jax-cuda13-plugin), found
  where JAX itself looks for them: modules of the `jax_plugins` namespace package and `jax_plugins` entry
  points."""
  import importlib.metadata
  import pkgutil
  names = {entry.name for entry in importlib.metadata.entry_points(group="jax_plugins")}
  try:
    import jax_plugins
    names |= {module.name for module in pkgutil.iter_modules(jax_plugins.__path__)}
  except ImportError:
    pass
  return names


def keep_off_absent_tpu() -> bool:
  """Leaves the TPU runtime alone where it is installed but no TPU chip is: returns whether it did so.

  With libtpu installed (the `tpu` extra, for the pod compile tool), JAX would try to start a TPU backend
  on every run, printing pages of TPU initialisation errors on a machine without one before it falls back
  to the CPU. Where no TPU chip is attached, no platform was chosen (JAX_PLATFORMS), no other plugin (a GPU's)
  is installed and the CPU is the only other backend, this picks the CPU, so that a CPU run with the extra
  behaves exactly as one without it. Must run before the first JAX computation.
  """
  if os.environ.get("JAX_PLATFORMS") or jax.config.jax_platforms:
    return False
  if pjrt_plugins():
    # A GPU (or other) plugin registers its backend only when JAX starts its backends, after this runs: the
    # factories below would list only the CPU and the TPU, and this would keep a GPU machine on its CPU.
    return False
  try:
    from jax._src import hardware_utils, xla_bridge  # no public way to list the backends before they start
    # Backends JAX may pick by itself: not those of negative priority, which it starts only when named (JAX
    # 0.12's "proxy", for an IFRT proxy server, fails at once without one).
    factories = {name for name, registration in xla_bridge._backend_factories.items()
                 if getattr(registration, "priority", 0) >= 0}
    chips, _ = hardware_utils.num_available_tpu_chips_and_device_id()
  except Exception:  # a JAX whose internals moved: leave JAX's own choice
    return False
  if "tpu" not in factories or chips > 0 or factories - {"tpu"} != {"cpu"}:
    return False
  jax.config.update("jax_platforms", "cpu")
  return True


def _on_cloud_tpu_vm() -> bool:
  """True on a Cloud TPU VM (JAX found TPU chips and libtpu at import), where initialize() needs no
  arguments: it reads the pod's workers from the VM's metadata (a single-host VM makes a pod of one)."""
  if "," in os.environ.get("TPU_WORKER_HOSTNAMES", ""):
    return True
  try:
    from jax._src import cloud_tpu_init  # set while `import jax` ran; no public equivalent
  except ImportError:
    return False
  return bool(getattr(cloud_tpu_init, "running_in_cloud_tpu_vm", False))


def make_mesh(devices=None, num_slices: int | None = None, regions: int = 1) -> Mesh:
  """The run's mesh over every device of every host (or over `devices`, e.g. a TPU topology's for an
  ahead-of-time compile); batches are split over all of its devices.

  One slice (the usual case): a 1-D mesh, its one axis DATA_AXIS. Several slices (TPU multi-slice, chips of
  several slices joined by the data-centre network, DCN): a 2-D mesh (SLICE_AXIS, DATA_AXIS) of shape
  (slices, devices per slice), the slice axis major, as jax.experimental.mesh_utils.create_hybrid_device_mesh
  lays a DCN axis out. `num_slices`: the slice count (the config's mesh.slices); None (or 0) takes what the
  devices report (TPU devices carry `slice_index`; CPU devices none: one slice). On a CPU, a count above 1
  simulates slices: the devices in order are cut into that many equal blocks.

  Devices are ordered slice by slice, then host by host (process index, then device id): each host's devices
  then hold one contiguous block of the global batch, the rows local_slice gives it, also across slices (the
  batch is split over the flattened (slice, device) index). (jax.make_mesh and create_hybrid_device_mesh order
  a slice's chips along the torus instead, which interleaves hosts, e.g. 0,0,1,1,1,1,0,2,... on a v5e 4x4, and
  the rows a host loads would not be the rows its chips hold. The step's gradient mean, over every chip, does
  not depend on the order.)

  `regions` > 1 (model.regions, NeRF-XL): one more axis, REGION_AXIS, the minor one, of that size: each
  region's fields live on the devices at its place on it, and neighbouring devices (one host's, where
  `regions` divides its device count) hold the regions of the same rays, whose partial sums they exchange at
  every step. A batch is split over the other axes and the same on every device of the region axis.
  """
  devices = list(jax.devices() if devices is None else devices)
  reported = sorted({getattr(d, "slice_index", 0) for d in devices})
  slices = num_slices or len(reported)
  if slices < 1:
    raise UserError(f"mesh.slices={slices} must be 0 (the slices the devices report) or a positive count.")
  if len(reported) > 1 and slices != len(reported):
    raise UserError(f"mesh.slices={slices} but the {len(devices)} devices are in {len(reported)} slices; leave "
                    f"--config.mesh.slices=0 to take the slices the devices report.")
  if len(devices) % slices:
    raise UserError(f"{len(devices)} devices do not split into mesh.slices={slices} slices of equal size; make "
                    f"mesh.slices a divisor of the device count (or 0 for the slices the devices report).")
  per_slice = len(devices) // slices
  if regions < 1 or per_slice % regions:
    raise UserError(f"model.regions={regions} does not split over the {per_slice} devices of a slice; make it a "
                    f"divisor of {per_slice} (or 1).")
  ordered = sorted(devices, key=lambda d: (getattr(d, "slice_index", 0), d.process_index, d.id))
  if regions > 1:
    shape, names = (per_slice // regions, regions), (DATA_AXIS, REGION_AXIS)
    if slices > 1:
      shape, names = (slices,) + shape, (SLICE_AXIS,) + names
    return Mesh(np.array(ordered).reshape(shape), names, axis_types=(AxisType.Explicit,) * len(names))
  if slices == 1:  # exactly today's single-slice mesh
    return Mesh(np.array(ordered), (DATA_AXIS,), axis_types=(AxisType.Explicit,))  # as jax.make_mesh's
  return Mesh(np.array(ordered).reshape(slices, len(devices) // slices), (SLICE_AXIS, DATA_AXIS),
              axis_types=(AxisType.Explicit, AxisType.Explicit))


def batch_axes(mesh: Mesh):
  """The mesh axes a batch is split over (all of them but REGION_AXIS): DATA_AXIS on one slice,
  (SLICE_AXIS, DATA_AXIS) on several; what shard_map's specs, the gradient mean and axis_index take."""
  names = tuple(n for n in mesh.axis_names if n != REGION_AXIS)
  return names[0] if len(names) == 1 else names


def batch_axis_sizes(mesh: Mesh) -> tuple:
  """The sizes of the batch's axes (batch_axes), major first."""
  return tuple(mesh.shape[n] for n in mesh.axis_names if n != REGION_AXIS)


def batch_devices(mesh: Mesh) -> int:
  """How many parts a batch is split into (the devices of a region, or all of them without regions)."""
  return int(np.prod(batch_axis_sizes(mesh)))


def num_regions(mesh: Mesh) -> int:
  return mesh.shape.get(REGION_AXIS, 1)


def gather_regions(tree):
  """Inside shard_map: each device's (L, R, ...) leaves -> the (L x region axis, R, ...) leaves of every device of
  the region axis, in the axis' order, formally the same on all of them (invariant). Its transpose hands each
  device the slice of the cotangent that is its own, with no communication; jax.lax.all_gather's default result
  (to="varying") would vary over the axis instead, and its transpose (a reduce-scatter) would sum every device's cotangent: the
  gradients of a loss that every device of the axis computes alike would come out (axis size) times too
  large. (to="invarying" relies on shard_map's check_vma, on by default; JAX 0.12 no longer has the private
  all_gather_invariant this once called.)"""
  import jax.numpy as jnp
  # One gather per dtype for the whole tree (each leaf's trailing axes flattened and packed side by side):
  # a collective's fixed cost is per call, and the per-ray sums are several small leaves.
  leaves, treedef = jax.tree.flatten(tree)
  out = [None] * len(leaves)
  by_dtype: dict = {}
  for i, leaf in enumerate(leaves):
    by_dtype.setdefault(leaf.dtype, []).append(i)
  for members in by_dtype.values():
    lead = leaves[members[0]].shape[:2]
    packed = jnp.concatenate([leaves[i].reshape(lead + (-1,)) for i in members], axis=-1)
    gathered = jax.lax.all_gather(packed, REGION_AXIS, axis=0, tiled=True, to="invarying")
    offset = 0
    for i in members:
      width = int(np.prod(leaves[i].shape[2:], dtype=int))
      out[i] = gathered[..., offset:offset + width].reshape(gathered.shape[:1] + leaves[i].shape[1:])
      offset += width
  return jax.tree.unflatten(treedef, out)


def batch_spec(mesh: Mesh) -> P:
  """The PartitionSpec of a batch's leading axis split over every device of `mesh`."""
  return P(batch_axes(mesh))


def num_slices(mesh: Mesh) -> int:
  return mesh.shape.get(SLICE_AXIS, 1)


@functools.cache  # (made for every training step's batch)
def batch_sharding(mesh: Mesh) -> NamedSharding:
  return NamedSharding(mesh, batch_spec(mesh))


def replicated(mesh: Mesh) -> NamedSharding:
  return NamedSharding(mesh, P())


def local_slice(global_size: int, mesh: Mesh | None = None) -> slice:
  """This process's contiguous share of a global batch of `global_size` rows laid over `mesh` (default: all
  devices of all hosts; process order = mesh order). On a mesh of this process's own devices: every row.
  On a mesh with a region axis, the rows of the batch parts its devices hold (processes that share a part,
  a region axis spanning them, load the same rows)."""
  if mesh is not None and REGION_AXIS in mesh.axis_names:
    parts = batch_devices(mesh)
    if global_size % parts:
      raise UserError(f"a global batch of {global_size} rays does not split evenly over {parts} devices (of a "
                      f"region); make train.batch_size a multiple of {parts}.")
    held = np.moveaxis(mesh.devices, list(mesh.axis_names).index(REGION_AXIS), -1).reshape(parts, -1)
    mine = [i for i in range(parts) if any(d.process_index == jax.process_index() for d in held[i])]
    per_part = global_size // parts
    return slice(mine[0] * per_part, (mine[-1] + 1) * per_part)
  devices = jax.devices() if mesh is None else list(mesh.devices.flat)
  processes = sorted({d.process_index for d in devices})
  if global_size % len(devices) != 0:
    raise UserError(f"a global batch of {global_size} rays does not split evenly over "
                    f"{len(devices)} devices; make train.batch_size a multiple of the device count.")
  per_process = global_size // len(processes)
  index = processes.index(jax.process_index())
  return slice(index * per_process, (index + 1) * per_process)


def local_shards(num_shards: int, mesh: Mesh | None = None) -> tuple[tuple[int, ...], int, int]:
  """(the data.shards this process holds, its index, the process count) over `mesh` (default: all devices of
  all hosts): process p of P holds shards [p S/P, (p+1) S/P), whose sub-batches are its local_slice rows.
  One shard (the default) is every frame, held by every process, each taking its rows of the one draw.
  Refuses a shard count above 1 that the process count does not divide."""
  devices = jax.devices() if mesh is None else list(mesh.devices.flat)
  processes = sorted({d.process_index for d in devices})
  index = processes.index(jax.process_index())
  if num_shards == 1:
    return (0,), index, len(processes)
  if num_shards % len(processes):
    multiple = -(-num_shards // len(processes)) * len(processes)
    raise UserError(f"data.shards={num_shards} does not split over the {len(processes)} hosts of this run; make "
                    f"it a multiple of the host count (e.g. --config.data.shards={multiple}), and of every host "
                    f"count the run may be resumed on.")
  per_process = num_shards // len(processes)
  return tuple(range(index * per_process, (index + 1) * per_process)), index, len(processes)


def to_global(mesh: Mesh, local_tree):
  """Host-local batch slices (leading axis) -> global arrays sharded over the mesh's data axis. The whole tree
  in one call: with one process, one batched transfer instead of one per leaf (the training loop makes a batch
  every step, on the cores the step computes on). An explicit host -> device transfer: with several processes
  JAX builds the arrays through make_array_from_callback, whose puts jax.transfer_guard counts as implicit
  (with one process it is a jax.device_put), so the training loop's guard (train.TRANSFER_GUARD) allows it here."""
  with jax.transfer_guard_host_to_device("allow"):
    return jax.make_array_from_process_local_data(batch_sharding(mesh), jax.tree.map(np.asarray, local_tree))


def to_host(tree):
  """Arrays -> full NumPy arrays on this process: fetched where they are all on its own devices, else
  all-gathered across hosts (a collective: every process must call it)."""
  if all(x.is_fully_addressable for x in jax.tree.leaves(tree)):
    return jax.device_get(tree)
  return multihost_utils.process_allgather(tree, tiled=True)


def ordered_mean(tree, axis_name, axis_size):
  """The mean of `tree` over the devices of `axis_name`, inside shard_map, summed in an order that depends on
  the devices' indices only, not on how they are spread over processes or slices: the same bits on 1 process
  x 8 devices as on 2 x 4 or 8 x 1, and on 2 slices x 4 devices as on 1 x 8.

  (jax.lax.pmean leaves the order to the collective's implementation, which differs between devices of one
  process and devices of several; with Adam's tiny epsilon those round-off differences grow into visibly
  different hash-grid parameters.) With a power-of-two count: a butterfly of log2(N) exchanges, device i
  adding its partner i xor 2^k's partial sum in round k. Floating-point addition is commutative, so both
  partners compute the same bits, and after the last round every device holds the same sum of the same
  tree of additions. Otherwise: every device gathers all N values and adds them in index order. Either
  way the result is then made formally device-invariant by a psum in which every device but the first
  contributes exact zeros (x + 0 = x exactly, in any order).

  Several axes (`axis_name` a tuple of names, major first, `axis_size` the tuple of their sizes; a
  multi-slice mesh's (SLICE_AXIS, DATA_AXIS)): the devices are indexed by the flattened index
  i = slice * D + device, as the batch is split. With D and the slice count S powers of two, the low log2(D)
  bits of i are the device within its slice and the high bits the slice, so the butterfly's rounds over the
  flattened index are exactly a within-slice stage (rounds over DATA_AXIS, partners in the same slice: ICI)
  followed by a cross-slice stage (rounds over SLICE_AXIS, partners at the same place in other slices: DCN).
  Each round adds the same partial sums as the 1-D butterfly over S x D devices: 2 slices x 4 devices give
  the bits of 1 x 8. Otherwise the gather over all axes is in the flattened order, the same sum again.
  """
  import jax.numpy as jnp
  names = tuple(axis_name) if isinstance(axis_name, (tuple, list)) else (axis_name,)
  sizes = tuple(axis_size) if isinstance(axis_size, (tuple, list)) else (axis_size,)
  total_size = int(np.prod(sizes))
  axes = names if len(names) > 1 else names[0]
  if total_size == 1:
    return jax.lax.pmean(tree, axes)  # no sum at all; pmean only marks the value device-invariant
  index = jax.lax.axis_index(axes)

  def mean(x):
    if total_size & (total_size - 1) == 0:
      total = x
      for name, size in reversed(tuple(zip(names, sizes))):  # the minor axis first: the low bits of i
        bit = 1
        while bit < size:
          total = total + jax.lax.ppermute(total, name, [(i, i ^ bit) for i in range(size)])
          bit <<= 1
    else:
      gathered = jax.lax.all_gather(x, axes)
      total = gathered[0]
      for i in range(1, total_size):
        total = total + gathered[i]
    total = total / total_size
    return jax.lax.psum(jnp.where(index == 0, total, jnp.zeros_like(total)), axes)

  # One exchange per dtype for the whole tree, not one per leaf: each collective has a fixed cost (across
  # processes on a CPU, a round trip), and a model's gradients are tens of leaves. The additions are
  # elementwise, so packing the leaves into one vector changes no bit of any sum.
  leaves, treedef = jax.tree.flatten(tree)
  leaves = [jnp.asarray(leaf) for leaf in leaves]
  by_dtype: dict = {}
  for i, leaf in enumerate(leaves):
    by_dtype.setdefault(leaf.dtype, []).append(i)
  out = [None] * len(leaves)
  for members in by_dtype.values():
    packed = mean(jnp.concatenate([leaves[i].reshape(-1) for i in members]))
    offset = 0
    for i in members:
      out[i] = packed[offset:offset + leaves[i].size].reshape(leaves[i].shape)
      offset += leaves[i].size
  return jax.tree.unflatten(treedef, out)
