"""KeyFrame: a frame kept in the map (ORB-SLAM2 ``KeyFrame``), array-wise.

Per keypoint: ``point_ids`` (map point, -1 none) and ``obs_row`` (its row in the
map's observation table).  ``covis`` is this keyframe's row of the covisibility
graph: ``{keyframe id: number of shared map points}``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..datatypes import StereoCalibration
from .geometry import camera_center, inv_T
from .frame import KeypointSet
from .matcher import KeypointGrid


@dataclass
class KeyFrame(KeypointSet):
    id: int
    frame_index: int
    uv: np.ndarray
    octave: np.ndarray
    angle: np.ndarray
    desc: np.ndarray
    u_right: np.ndarray
    depth: np.ndarray
    calib: StereoCalibration
    T_cw: np.ndarray
    point_ids: np.ndarray = field(default=None)  # type: ignore[assignment]
    obs_row: np.ndarray = field(default=None)  # type: ignore[assignment]
    covis: dict[int, int] = field(default_factory=dict)
    bad: bool = False
    _grid: KeypointGrid | None = None
    _desc64: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.uv)
        if self.point_ids is None:
            self.point_ids = np.full(n, -1, np.int64)
        if self.obs_row is None:
            self.obs_row = np.full(n, -1, np.int64)


    @property
    def center(self) -> np.ndarray:
        return camera_center(self.T_cw)

    @property
    def T_wc(self) -> np.ndarray:
        return inv_T(self.T_cw)

    def unproject(self, idx: np.ndarray) -> np.ndarray:
        K = self.calib.K
        z = self.depth[idx]
        x = (self.uv[idx, 0] - K[0, 2]) * z / K[0, 0]
        y = (self.uv[idx, 1] - K[1, 2]) * z / K[1, 1]
        Xc = np.stack([x, y, z], axis=1)
        return (Xc - self.T_cw[:3, 3]) @ self.T_cw[:3, :3]

    def best_covisibles(self, n: int | None = None, min_weight: int = 0) -> list[int]:
        items = sorted(((w, k) for k, w in self.covis.items() if w >= min_weight), key=lambda t: (-t[0], t[1]))
        ids = [k for _, k in items]
        return ids if n is None else ids[:n]
