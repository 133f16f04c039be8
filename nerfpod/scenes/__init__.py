"""Scene loaders. `load(config.data)` returns a Scene whatever the format."""
from nerfpod.errors import UserError
from nerfpod.scenes.base import Scene, Split

__all__ = ["Scene", "Split", "load"]


def load(data_config) -> Scene:
  """The scene that `config.data` names: kind 'procedural', 'tiny' (npz) or 'blender' (a scene folder)."""
  kind = data_config.kind
  if kind == "procedural":
    from nerfpod.scenes import procedural
    return procedural.load(data_config.image_size, pixel_center=data_config.pixel_center)
  if not data_config.path:
    raise UserError(f"data.kind={kind!r} needs a data path; pass --config.data.path=...")
  if kind == "tiny":
    from nerfpod.scenes import tiny
    scene = tiny.load(data_config.path)
    if data_config.downscale != 1:
      raise UserError("data.downscale is not supported for the 100x100 Tiny NeRF data; leave it at 1.")
    return scene
  if kind == "blender":
    from nerfpod.scenes import blender
    return blender.load(data_config.path, data_config.downscale)
  raise UserError(f"unknown data.kind {kind!r}; use 'procedural', 'tiny' or 'blender'.")
