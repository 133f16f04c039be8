"""Scene loaders. `load(config.data)` returns a Scene whatever the format.

    formats     the one table of formats, LOADERS: each one's loader, what it holds, how its files are told
    base        the one Scene type (splits of images, per-frame cameras, bounds, space), shards per host
    procedural  the built-in scene (no download)
    street      the built-in large scene: a street with its cameras along it (model.regions)
    tiny        the Tiny NeRF npz
    blender     the NeRF synthetic scenes (transforms_{train,val,test}.json)
    capture     what real captures share: normalised poses, bounds, the held-out frames
    llff        LLFF's poses_bounds.npy
    colmap      a COLMAP sparse model (pycolmap)
    nerfstudio  a nerfstudio / instant-ngp transforms.json

Everything format-specific stays in its loader: cameras are converted to one convention at load time, so
that everything downstream is format-blind.
"""
import dataclasses
import importlib

from absl import logging

from nerfpod import storage
from nerfpod.errors import UserError
from nerfpod.scenes.base import SPACES, Scene, Shards, Split, with_pose_noise
from nerfpod.scenes.formats import COLMAP_MODEL, LOADERS, Loader

__all__ = ["CAPTURE_KINDS", "KINDS", "LOADERS", "Loader", "SPACES", "Scene", "Shards", "Split", "cameras_only",
           "detect", "load"]

KINDS = tuple(LOADERS) + ("auto",)  # data.kind's values ('auto': told by data.path's files, detect())
CAPTURE_KINDS = tuple(kind for kind, loader in LOADERS.items() if loader.capture)
IN_MEMORY_KINDS = tuple(kind for kind, loader in LOADERS.items() if loader.in_memory)
# Whether a format's images carry alpha: what the pod compile tool needs to know of a scene without loading it.
HAS_ALPHA = {kind: loader.has_alpha for kind, loader in LOADERS.items()}


def detect(path: str) -> str:
  """The format of the file or folder at `path`, from what it holds, by each format's `files` and `endings` in
  LOADERS (scenes.formats), the lowest `precedence` first where a folder shows several: a COLMAP sparse model
  (sparse/0/, sparse/ or the folder itself) -> colmap, also where a transforms.json (as nerfpod prepare writes
  beside the model) or an LLFF poses_bounds.npy (multinerf too prefers COLMAP's poses) is beside it;
  transforms.json -> nerfstudio, poses_bounds.npy -> llff, transforms_train.json -> blender, an .npz file -> tiny;
  a .json file is taken as a nerfstudio transforms file.

  An incomplete COLMAP model (sparse/0/ lacking one of cameras, images, points3D) is skipped with a warning
  that names the missing files, in favour of a transforms.json or poses_bounds.npy beside it (the same
  capture's poses, written from that model by nerfpod prepare or LLFF's imgs2poses); with nothing else
  there it is refused, naming them. data.kind=colmap insists on the model."""
  by_precedence = sorted(LOADERS.items(), key=lambda item: item[1].precedence)
  if storage.isfile(path):
    found = next((kind for kind, loader in by_precedence if path.endswith(loader.endings)), None)
    if found is not None:
      return found
  elif storage.isdir(path):
    from nerfpod.scenes import colmap

    def holds(name: str) -> bool:
      return colmap.model_folder(path) is not None if name == COLMAP_MODEL else storage.isfile(
          storage.join(path, name))
    found = next(((kind, name) for kind, loader in by_precedence for name in loader.files if holds(name)), None)
    broken = colmap.incomplete_model(path) if found is None or found[1] != COLMAP_MODEL else None
    if broken is not None:
      folder, missing = broken
      if found is None:
        raise UserError(f"{path} holds an incomplete COLMAP model and no other scene: in {folder}, "
                        f"{colmap.missing_files(missing)}; restore {'it' if len(missing) == 1 else 'them'} or "
                        f"re-export the model from COLMAP.")
      logging.warning("data.kind=auto: found a COLMAP model in %s but %s, so it is skipped; using %s (%s) "
                      "instead (set data.kind=colmap to use the model once it is whole)", folder,
                      colmap.missing_files(missing), found[1], found[0])
    if found is not None:
      return found[0]
  else:
    raise UserError(f"data.path {path!r} not found; set --config.data.path to a scene folder or file.")
  names = [name for _, loader in by_precedence for name in loader.files]
  raise UserError(f"cannot tell the format of {path!r}: it holds none of {', '.join(names)}; set "
                  f"--config.data.kind to one of {', '.join(k for k in KINDS if k not in ('auto', 'procedural'))}.")


def cameras_only(data_config) -> Scene:
  """A built-in scene (a kind whose loader needs no data.path: procedural, street) with the cameras and poses
  load() gives it and its images left untraced (every pixel the background; its module's cameras()): for a tool
  that reads only the cameras (nerfpod aot's model.region_capacity=auto), without tracing every frame. Another kind is a ValueError
  (its cameras are in its files: load() it)."""
  loader = LOADERS.get(data_config.kind)
  if loader is None or loader.needs_path:
    raise ValueError(f"cameras_only: data.kind={data_config.kind} is not a built-in scene")
  return importlib.import_module(f"nerfpod.scenes.{loader.module}").cameras(data_config.path, data_config)


def load(data_config, shards: Shards | None = None) -> Scene:
  """The scene that `config.data` names: kind 'procedural', 'tiny' (npz), 'blender' (a scene folder), a real
  capture ('llff', 'colmap', 'nerfstudio'), or 'auto' (detected from data.path, and printed).
  The config's fields were checked by nerfpod.schema; what is checked here is the data.

  `shards`: the training frames this host holds (data.shards) and its memory budget, checked before any
  image is read; files are read for those frames only. The scenes made in memory (procedural, tiny) are
  made whole, then checked and cut to the shard. None: every frame, unchecked.

  data.path may be local or a URL (gs://bucket/scene): every format is read through nerfpod.storage."""
  storage.forget_listings()  # a bucket's folders as they are now
  scene = _load(data_config, shards)
  if data_config.get("pose_noise"):  # a data config made by hand may lack the field
    scene = with_pose_noise(scene, *data_config.pose_noise, data_config.get("pose_noise_seed", 0))
  if shards is None or scene.kind not in IN_MEMORY_KINDS:
    return scene
  train = scene.split("train")  # made in memory: check and cut it now
  frame_bytes = train.cameras.num_pixels * (3 + (train.alphas is not None))
  heldout = {id(v): v for k, v in scene.splits.items() if k != "train"}.values()
  shards.check(frame_bytes, sum(v.nbytes for v in heldout), scene.name)
  if shards.count == 1:
    return scene
  return dataclasses.replace(scene, splits={**scene.splits, "train": train.keep(shards.frames(len(train)))})


def _load(data_config, shards: Shards | None) -> Scene:
  kind, path = data_config.kind, data_config.path
  if kind != "auto" and kind not in LOADERS:
    raise UserError(f"unknown data.kind {kind!r}; use one of {', '.join((*LOADERS, 'auto'))}.")
  if (kind == "auto" or LOADERS[kind].needs_path) and not path:
    raise UserError(f"data.kind={kind!r} needs a data path; pass --config.data.path=...")
  if kind == "auto":
    kind = detect(path)
    import jax  # started by now; only process 0 talks
    if jax.process_index() == 0:
      print(f"data.kind=auto: {path} holds a scene of kind {kind!r}", flush=True)
  loader = LOADERS[kind]
  if loader.capture and not storage.exists(path):
    raise UserError(f"data.path {path!r} not found; set --config.data.path to the {kind} capture's folder.")
  module = importlib.import_module(f"nerfpod.scenes.{loader.module}")
  return module.load(path, data_config, shards)
