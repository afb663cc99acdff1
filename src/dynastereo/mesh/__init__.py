"""The dense, mover-free mesh of the static world (``run --save-mesh``): TSDF fusion of the
keyframes' disparity outside the movers' masks, at the final poses, and marching cubes.

:mod:`.fusion` (what is fused and how), :mod:`.tsdf` (the compiled volume), :mod:`.tables`
(marching cubes' cases), :mod:`.ply` (the files), :mod:`.render` (pictures of it).
"""

from .fusion import DenseResult, KeyframeRecorder, KeyframeView, MeshStats, fuse, fuse_system
from .ply import read_ply, write_cloud_ply, write_mesh_ply
from .tsdf import Mesh, TSDFVolume

__all__ = ["DenseResult", "KeyframeRecorder", "KeyframeView", "Mesh", "MeshStats", "TSDFVolume", "fuse",
           "fuse_system", "read_ply", "write_cloud_ply", "write_mesh_ply"]
