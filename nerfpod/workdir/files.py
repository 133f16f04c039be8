"""The workdir's own files: config.json (the resolved config), scene.json, regions.json (a region model's
regions, written and read back), and the checks of a workdir.

    check_workdir      a --workdir that is a file, or cannot be written (training), in one sentence
    check_compatible   a workdir whose checkpoints came from a config of another shape or data is refused
    read_config        a run's config from its config.json, checked by the schema (the viewer, exports)
    write_regions, read_regions   regions.json: a region model's planes (a resume compares its own with them)
    write_json         whole or not at all (PATH.tmp, then renamed); also eval/metrics.json

Paths go through nerfpod.storage.path, so a workdir may be a gs:// bucket. The checkpoints themselves are
nerfpod.workdir.checkpoints'.
"""
import json
import os

import ml_collections

from nerfpod import schema, storage
from nerfpod.errors import UserError

def incompatible_fields(saved: dict, current: dict) -> list[str]:
  """Dotted names of config fields that differ between a workdir's config and this run's, bar those the schema
  lets change on resuming (schema.RESUMABLE). A field the saved config lacks counts as its schema default
  (with_defaults)."""
  a, b = schema.flatten(with_defaults(saved)), schema.flatten(current)
  differing = sorted(k for k in set(a) | set(b) if a.get(k, "<absent>") != b.get(k, "<absent>"))
  return [k for k in differing if not schema.resumable(k)]


# Fields added after workdirs were written whose default is not what those runs did: what a workdir's
# config.json without the field ran with (a resume keeps its optimiser; the tools read the run it was).
WHEN_ABSENT = {"train": {"pose_gate": 0.0, "pose_b1": 0.9}}


def with_defaults(saved: dict) -> dict:
  """`saved` (a workdir's config.json, as JSON loads it) with each field it lacks at its schema default, in
  the same JSON form (a tuple is the list config.json holds): a field added after the workdir was written
  (train.pose_pin_mean, say) is one whose default is what that run did, for a resume and for the tools that
  read the workdir alike; where it is not, WHEN_ABSENT says what the run did. What `saved` holds wins, fields
  this version does not know included (the schema refuses those)."""
  def merge(defaults: dict, given: dict) -> dict:
    out = dict(defaults)
    for key, value in given.items():
      out[key] = merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out
  return merge(merge(json.loads(schema.defaults().to_json_best_effort()), WHEN_ABSENT), saved)


def check_workdir(workdir: str, writable: bool) -> None:
  """Refuses, in one sentence each, a --workdir that is a file, or (`writable`: training) one that cannot be
  made or written. gs:// paths are left to their own errors."""
  if storage.is_url(workdir):
    return
  path = storage.path(workdir)
  if path.exists() and not path.is_dir():
    raise UserError(f"--workdir={workdir} is an existing file, not a folder; pass a folder (a new one for a new "
                    f"run).")
  if not writable:
    return
  try:
    path.mkdir(parents=True, exist_ok=True)
    probe = path / f".nerfpod-write-test-{os.getpid()}"
    probe.write_text("")
    probe.unlink()
  except OSError as e:
    raise UserError(f"--workdir={workdir} cannot be written ({e.strerror or e}); pass a folder this user may "
                    f"write, or fix its permissions.") from None


def saved_config(workdir: str) -> dict | None:
  """The workdir's config.json, None where there is none; a malformed one is a UserError."""
  path = storage.path(workdir) / "config.json"
  if not path.exists():
    return None
  try:
    saved = json.loads(path.read_text())
    if not isinstance(saved, dict):
      raise ValueError("not a JSON object")
  except (ValueError, UnicodeDecodeError) as e:
    raise UserError(f"{path} is not valid JSON ({e}); restore it (it records the config the checkpoints were "
                    f"trained with) or move it away to resume with this run's config.") from None
  return saved


def check_compatible(workdir: str, config_json: dict, has_checkpoint: bool) -> None:
  """Refuses to resume a workdir whose checkpoints (`has_checkpoint`) came from a config of another shape or
  data, or whose config.json is gone (its checkpoints' config unknown)."""
  saved = saved_config(workdir)
  if not has_checkpoint:
    return
  if saved is None:  # (a run writes config.json before its first step: it was deleted, or never copied along)
    raise UserError(f"workdir {workdir} holds checkpoints but no config.json, the config they were trained with, "
                    f"so nothing can tell whether this run's config fits them; put that config.json back, or use a "
                    f"new --workdir.")
  differing = incompatible_fields(saved, config_json)
  if differing:
    was, now = schema.flatten(saved), schema.flatten(config_json)
    shown = ", ".join(f"{k} ({was.get(k, '<absent>')!r} -> {now.get(k, '<absent>')!r})"
                      for k in differing[:6])
    more = f" and {len(differing) - 6} more" if len(differing) > 6 else ""
    resumable = ", ".join(schema.resumable_names())
    raise UserError(f"workdir {workdir} holds checkpoints of a different config: {shown}{more}; use a new "
                    f"--workdir, or the settings of the workdir's config.json (only {resumable} may change on "
                    f"resuming).")


def write_json(path, value, sort_keys: bool = False) -> None:
  """Writes `value` as indented JSON to `path` (local or gs://) whole or not at all: a local file into
  PATH.tmp, then renamed (the folder created); an object in a bucket in one upload, which creates it whole or
  not at all (a bucket has no rename: it would copy the object and delete the first)."""
  path = storage.path(path)
  # allow_nan=False: a NaN or infinity is an error here, not a bare NaN that strict JSON parsers refuse.
  text = json.dumps(value, indent=2, sort_keys=sort_keys, allow_nan=False)
  if storage.is_url(path):
    path.write_text(text)
    return
  path.parent.mkdir(parents=True, exist_ok=True)
  tmp = path.parent / f"{path.name}.tmp"
  try:
    tmp.write_text(text)
    tmp.replace(path)
  except BaseException:  # a full disk, an interruption: no half-written PATH.tmp is left behind
    try:
      tmp.unlink(missing_ok=True)
    except OSError:
      pass
    raise


def write_config(workdir: str, config_json: dict) -> None:
  """Writes workdir/config.json (the resolved config) whole or not at all; call on process 0 only."""
  write_json(storage.path(workdir) / "config.json", config_json, sort_keys=True)


def write_scene(workdir: str, scene_json: dict) -> None:
  """Writes workdir/scene.json (the scene's name, format, space, ray bounds and the capture -> scene
  similarity, so that renders and exports can be mapped back to a capture's frame); call on process 0 only."""
  write_json(storage.path(workdir) / "scene.json", scene_json)


def write_regions(workdir: str, cut: str, region_planes) -> None:
  """Writes workdir/regions.json: a region model's K convex regions (model.regions > 1, nerf/regions.py's
  Partition), each the points x with normal . x < offset (<= where closed) for each of its planes, so that
  a user or a tool sees where each field lives without the scene; call on process 0 only."""
  normals, offsets, closed = region_planes  # (K, P, 3), (K, P), (K, P): arrays or nested sequences
  write_json(storage.path(workdir) / "regions.json",
             {"cut": cut, "count": len(normals),
              "regions": [{"planes": [{"normal": list(map(float, n)), "offset": float(b), "closed": bool(c)}
                                      for n, b, c in zip(ns, bs, cs)]}
                          for ns, bs, cs in zip(normals, offsets, closed)]})


def read_regions(workdir: str) -> tuple[str, tuple] | None:
  """(cut, (normals (K, P, 3), offsets (K, P), closed (K, P)) as nested tuples, region_planes' form) of
  workdir/regions.json, or None where the workdir has none (a new run, a one-region model): what a resumed run
  compares its cut with (model.region_cut=balanced cuts from seeded rays, so the two agree unless the code or
  the scene changed)."""
  path = storage.path(workdir) / "regions.json"
  try:
    tree = json.loads(path.read_text())
  except FileNotFoundError:
    return None
  planes = [region["planes"] for region in tree["regions"]]
  return tree["cut"], (tuple(tuple(tuple(float(v) for v in p["normal"]) for p in ps) for ps in planes),
                       tuple(tuple(float(p["offset"]) for p in ps) for ps in planes),
                       tuple(tuple(bool(p["closed"]) for p in ps) for ps in planes))


def read_config(workdir: str) -> ml_collections.ConfigDict:
  """The run's config from workdir/config.json (a field it lacks, added since the run, at its default:
  with_defaults), checked by the schema; a missing, unreadable or unreachable one is one sentence. For the
  tools that take only a --workdir."""
  storage.check_reachable(workdir)  # no network: one sentence now, not after a bucket client's retries
  path = storage.path(workdir) / "config.json"
  try:
    text = path.read_text()
  except FileNotFoundError:
    bucket = storage.missing_bucket(workdir)
    if bucket is not None:
      raise UserError(f"workdir {workdir}: there is no bucket {bucket} (or these credentials cannot see it); "
                      f"check the --workdir path.") from None
    raise UserError(f"workdir {workdir} holds no config.json; pass the --workdir of a training run "
                    f"(it writes config.json when it starts).") from None
  except Exception as e:  # noqa: BLE001 (gs:// without credentials or network, permissions, ...)
    reason = " ".join(str(e).split())[:300] or type(e).__name__
    raise UserError(f"could not read {path} ({reason}); check the --workdir path and, for gs://, your "
                    f"network and credentials (gcloud auth application-default login).") from None
  try:
    tree = json.loads(text)
    if not isinstance(tree, dict):
      raise ValueError("not a JSON object")
  except ValueError as e:
    raise UserError(f"{path} is not valid JSON ({e}); pass the --workdir of a nerfpod training run.") from None
  config = ml_collections.ConfigDict(with_defaults(tree))
  try:
    schema.validate(config)
  except schema.ConfigError as e:  # its fixes name command-line overrides, which these tools do not take
    raise UserError(f"{path} holds a config this nerfpod version refuses ({e.messages[0]}"
                    f"{f' and {len(e.messages) - 1} more' if len(e.messages) > 1 else ''}); use the "
                    f"nerfpod version that trained it.") from None
  return config
