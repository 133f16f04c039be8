"""Scene loaders. `load(config.data)` returns a Scene whatever the format."""
from nerfpod.errors import UserError
from nerfpod.scenes.base import Scene, Split

__all__ = ["KINDS", "Scene", "Split", "load"]

KINDS = ("procedural", "tiny", "blender")
# Whether a format's images carry alpha (then training batches do too): what the pod compile tool needs to
# know of a scene without loading it.
HAS_ALPHA = {"procedural": True, "tiny": False, "blender": True}


def load(data_config) -> Scene:
  """The scene that `config.data` names: kind 'procedural', 'tiny' (npz) or 'blender' (a scene folder).
  The config's fields were checked by nerfpod.schema; what is checked here is the data."""
  kind = data_config.kind
  if kind not in KINDS:
    raise UserError(f"unknown data.kind {kind!r}; use one of {', '.join(KINDS)}.")
  if kind == "procedural":
    from nerfpod.scenes import procedural
    return procedural.load(data_config.image_size, pixel_center=data_config.pixel_center)
  if not data_config.path:
    raise UserError(f"data.kind={kind!r} needs a data path; pass --config.data.path=...")
  if kind == "tiny":
    from nerfpod.scenes import tiny
    return tiny.load(data_config.path)
  from nerfpod.scenes import blender
  return blender.load(data_config.path, data_config.downscale)
