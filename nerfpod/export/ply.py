"""PLY files (binary little-endian, the format MeshLab, Blender, Open3D and 3D Gaussian Splatting read):
points with optional normals and colours, and triangle faces; and OBJ for meshes.

    write_ply(path, points_Nx3, colours_Nx3=None, normals_Nx3=None, faces_Fx3=None, comments=())
    write_obj(path, points_Nx3, colours_Nx3=None, normals_Nx3=None, faces_Fx3=None, comments=())

Colours are float in [0, 1] (stored as uchar red, green, blue in PLY; as the widely read `v x y z r g b`
extension in OBJ). Paths may be local or gs:// (nerfpod.storage.path); the file is written whole or not at
all.
"""
import io

import numpy as np

from nerfpod import storage


def _uint8(colours) -> np.ndarray:
  return np.round(np.clip(np.asarray(colours, np.float64), 0.0, 1.0) * 255.0).astype(np.uint8)


def _write(path, data: bytes) -> None:
  path = storage.path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  tmp = path.parent / f"{path.name}.tmp"
  tmp.write_bytes(data)
  tmp.replace(path)


def ply_bytes(points_Nx3, colours_Nx3=None, normals_Nx3=None, faces_Fx3=None, comments=()) -> bytes:
  points = np.asarray(points_Nx3, np.float32).reshape(-1, 3)
  fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
  if normals_Nx3 is not None:
    fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
  if colours_Nx3 is not None:
    fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
  vertices = np.empty(len(points), dtype=fields)
  vertices["x"], vertices["y"], vertices["z"] = points.T
  if normals_Nx3 is not None:
    normals = np.asarray(normals_Nx3, np.float32).reshape(-1, 3)
    vertices["nx"], vertices["ny"], vertices["nz"] = normals.T
  if colours_Nx3 is not None:
    colours = _uint8(colours_Nx3).reshape(-1, 3)
    vertices["red"], vertices["green"], vertices["blue"] = colours.T
  names = {"<f4": "float", "u1": "uchar"}
  header = ["ply", "format binary_little_endian 1.0", *(f"comment {' '.join(str(c).split())}" for c in comments),
            f"element vertex {len(points)}", *(f"property {names[t]} {n}" for n, t in fields)]
  body = [vertices.tobytes()]
  if faces_Fx3 is not None:
    faces = np.asarray(faces_Fx3, np.int64).reshape(-1, 3)
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    rows = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    rows["n"], rows["v"] = 3, faces
    body.append(rows.tobytes())
  header.append("end_header")
  return ("\n".join(header) + "\n").encode("ascii") + b"".join(body)


def write_ply(path, points_Nx3, colours_Nx3=None, normals_Nx3=None, faces_Fx3=None, comments=()) -> None:
  _write(path, ply_bytes(points_Nx3, colours_Nx3, normals_Nx3, faces_Fx3, comments))


def write_obj(path, points_Nx3, colours_Nx3=None, normals_Nx3=None, faces_Fx3=None, comments=()) -> None:
  out = io.StringIO()
  for c in comments:
    out.write(f"# {' '.join(str(c).split())}\n")
  points = np.asarray(points_Nx3, np.float64).reshape(-1, 3)
  if colours_Nx3 is None:
    np.savetxt(out, points, fmt="v %.6f %.6f %.6f")
  else:
    colours = np.asarray(colours_Nx3, np.float64).reshape(-1, 3)
    np.savetxt(out, np.concatenate([points, np.clip(colours, 0, 1)], 1), fmt="v %.6f %.6f %.6f %.4f %.4f %.4f")
  if normals_Nx3 is not None:
    np.savetxt(out, np.asarray(normals_Nx3, np.float64).reshape(-1, 3), fmt="vn %.5f %.5f %.5f")
  if faces_Fx3 is not None:
    faces = np.asarray(faces_Fx3, np.int64).reshape(-1, 3) + 1  # OBJ counts from 1
    if normals_Nx3 is not None:
      np.savetxt(out, np.repeat(faces, 2, axis=1), fmt="f %d//%d %d//%d %d//%d")
    else:
      np.savetxt(out, faces, fmt="f %d %d %d")
  _write(path, out.getvalue().encode("ascii"))
