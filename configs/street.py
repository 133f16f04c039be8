"""The built-in large scene (nerfpod/scenes/street.py, no download): a 14-unit street of textured buildings,
trees and lamps, 120 training cameras along it, for fields bigger than one chip.

The default job's field and training (configs/default.py: an 8-level hash grid of 2^16 rows, one proposal
round of 32 intervals then 16 samples, 1,024 rays a step), over the street's box (model.hashgrid.bound 7.6)
at 80x80 pixels: one such field spreads its rows over the whole street and is short of capacity there.
`regions=K` gives K fields, each over its own region of the street (model.regions; the regions are the
Voronoi cells of k-means centres of the training cameras' ground positions, model.region_cut=cameras): K
times the parameters over the same scene, 1/K of them on each device of the region axis
(docs/scale.md#scenes-bigger-than-one-chip). The orbit is the ellipse through the cameras, along the street.
`blocks=B` (default 1: the street above, unchanged) makes the street B times as long (14 B units, 120 B
training cameras at the same spacing; data.path 'blocks=B' tells the loader), with the hash grid's box grown to
hold it (bound 7 B + 0.6) and the same field per region: a scene with something for K = 8 or 16 regions to
hold (e.g. `blocks=8,regions=8` and --config.model.region_cut=balanced, docs/scale.md).
Arguments: `regions=K` (default 1), `blocks=B` (default 1), `smoke` for tests.
"""
from nerfpod import config_util


def get_config(arg: str | None = None):
  args = config_util.parse_arg(arg, regions="1", blocks="1", smoke=False)
  default = config_util.sibling_module(__file__, "default")
  c = default.get_config()
  c.data.kind = "street"
  c.data.image_size = 80
  c.model.hashgrid.bound = 7.6       # the street's box: 14 units long, its ground 7 wide, 2.6 high
  blocks = int(args["blocks"])
  if blocks > 1:  # B blocks end to end: 14 B units long
    c.data.path = f"blocks={blocks}"
    c.model.hashgrid.bound = 7.0 * blocks + 0.6
  c.model.regions = int(args["regions"])
  c.model.region_cut = "cameras"
  c.orbit.path = "ellipse"
  if args["smoke"]:
    default.shrink_for_smoke(c)
  return c
