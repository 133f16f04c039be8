"""The one table of scene formats, LOADERS: data.kind -> what nerfpod knows of a format without loading a scene
(its loader module, whether its images carry alpha, whether it is a real capture and how its poses are framed
by default, how data.kind=auto recognises its files). Imports nothing of nerfpod's: every module of the package
may read it (scenes/__init__.py dispatches on it; capture.py frames a capture by it)."""
import dataclasses


@dataclasses.dataclass(frozen=True)
class Loader:
  """A scene format: its module here, imported only when a scene of the format is loaded (so that an optional
  extra, pycolmap, is needed only then), whose `load(path, data_config, shards) -> Scene` is the one loader
  signature; and what the rest of nerfpod knows of the format without loading a scene."""
  module: str               # nerfpod.scenes.<module>
  has_alpha: bool = False   # its images carry alpha (then training batches do): the pod tool's batch shapes
  capture: bool = False     # a real capture: poses normalised by data.orient/center/scale, data.llffhold
  in_memory: bool = False   # made whole in memory, then cut to a host's shard (else only its frames are read)
  needs_path: bool = True   # read from data.path
  # data.kind=auto (scenes.detect): a folder holding one of `files` (paths in it; "sparse/0/": a whole COLMAP
  # model there, in sparse/ or in the folder itself, scenes.colmap.model_folder), or a file whose name ends in
  # one of `endings`, is of this format. Where a folder shows several formats, the lowest `precedence` wins.
  files: tuple[str, ...] = ()
  endings: tuple[str, ...] = ()
  precedence: int = 0
  # A capture's framing where data.orient, data.center and data.scale are 'auto' (scenes.capture.normalization):
  # the rotation, the centre, and whether the scale comes from the nearest bound (where the format has bounds)
  # rather than from the farthest camera.
  auto_orient: str = "up"
  auto_center: str = "focus"
  scale_by_bounds: bool = False


COLMAP_MODEL = "sparse/0/"  # a Loader's `files` entry: a whole COLMAP model (scenes.colmap.model_folder)

# data.kind -> its loader: adding a format is an entry here and its module (docs/architecture.md).
LOADERS = {
    "procedural": Loader("procedural", has_alpha=True, in_memory=True, needs_path=False),
    "street": Loader("street", has_alpha=True, in_memory=True, needs_path=False),
    "tiny": Loader("tiny", in_memory=True, endings=(".npz",)),
    "blender": Loader("blender", has_alpha=True, files=("transforms_train.json",), precedence=3),
    # The original LLFF code's framing: recentred on the average camera, scaled by 1 / (0.75 min near).
    "llff": Loader("llff", capture=True, files=("poses_bounds.npy",), precedence=2, auto_orient="llff",
                   auto_center="poses", scale_by_bounds=True),
    # COLMAP's poses first where a transforms.json or poses_bounds.npy is beside the model (multinerf too).
    "colmap": Loader("colmap", capture=True, files=(COLMAP_MODEL,), precedence=0),
    "nerfstudio": Loader("nerfstudio", capture=True, files=("transforms.json",), endings=(".json",), precedence=1),
}
