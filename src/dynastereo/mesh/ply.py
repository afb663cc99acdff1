"""The mesh and the dense cloud as binary PLY files (atomic writes).

``write_mesh_ply``: vertices (float32 x, y, z; uchar red, green, blue) and triangles
(``vertex_indices``, uchar count + int32 indices); ``write_cloud_ply``: the same vertices,
no faces.  Both read back with Open3D, plyfile, MeshLab, CloudCompare.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import OutputError
from ..io.outputs import atomic_open
from .tsdf import Mesh

_VERTEX = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
_FACE = np.dtype([("n", "u1"), ("i", "<i4", (3,))])


def _write(path: str | Path, mesh: Mesh, faces: bool, what: str) -> Path:
    v = np.empty(len(mesh.vertices), _VERTEX)
    for k, name in enumerate("xyz"):
        v[name] = mesh.vertices[:, k]
    for k, name in enumerate(("red", "green", "blue")):
        v[name] = mesh.colors[:, k]
    head = ["ply", "format binary_little_endian 1.0", f"comment dynastereo static world {what}",
            f"element vertex {len(v)}", "property float x", "property float y", "property float z",
            "property uchar red", "property uchar green", "property uchar blue"]
    f = None
    if faces:
        f = np.empty(len(mesh.faces), _FACE)
        f["n"] = 3
        f["i"] = mesh.faces
        head += [f"element face {len(f)}", "property list uchar int vertex_indices"]
    head.append("end_header")
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_open(path, "wb", fsync=False, mkdir=False) as fh:
            fh.write(("\n".join(head) + "\n").encode("ascii"))
            fh.write(v.tobytes())
            if f is not None:
                fh.write(f.tobytes())
    except OSError as e:
        raise OutputError(f"cannot write the {what}: {e.strerror}", path) from None
    return path


def write_mesh_ply(path: str | Path, mesh: Mesh) -> Path:
    return _write(path, mesh, True, "mesh")


def write_cloud_ply(path: str | Path, mesh: Mesh) -> Path:
    return _write(path, mesh, False, "dense cloud")


def read_ply(path: str | Path) -> Mesh:
    """A PLY this module wrote (its own layout only), back as a :class:`Mesh`."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    head = data[:end].decode("ascii").splitlines()
    nv = next(int(h.split()[2]) for h in head if h.startswith("element vertex"))
    nf = next((int(h.split()[2]) for h in head if h.startswith("element face")), 0)
    v = np.frombuffer(data, _VERTEX, nv, end)
    f = np.frombuffer(data, _FACE, nf, end + nv * _VERTEX.itemsize)
    return Mesh(np.stack([v["x"], v["y"], v["z"]], 1), f["i"].astype(np.int32),
                np.stack([v["red"], v["green"], v["blue"]], 1))
