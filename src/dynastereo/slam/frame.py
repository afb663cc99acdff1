"""Frame: one stereo pair's features, stereo depths, matches and pose (ORB-SLAM2 ``Frame``).

Everything per keypoint is an array: ``uv`` (N, 2), ``octave``, ``angle``, ``desc``
(N, 32) uint8, ``u_right`` / ``depth`` (-1 where no stereo match), and the tracking
state ``point_ids`` (map point of each keypoint, -1 none) with ``match_xyz`` (the
world position used for that match, which also covers the temporary "visual odometry"
points made from the previous frame's stereo depths), ``outlier``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..datatypes import StereoCalibration
from .geometry import desc_u64, inv_T
from .matcher import KeypointGrid
from .orb import Features


class KeypointSet:
    """What frames and keyframes share: keypoints ``uv`` with descriptors ``desc``, a lazily
    built search grid and the descriptors packed as uint64 words for Hamming distances."""

    uv: np.ndarray
    desc: np.ndarray
    calib: StereoCalibration
    _grid: KeypointGrid | None
    _desc64: np.ndarray | None

    def __len__(self) -> int:
        return len(self.uv)

    @property
    def grid(self) -> KeypointGrid:
        if self._grid is None:
            self._grid = KeypointGrid(self.uv, self.calib.width, self.calib.height)
        return self._grid

    @property
    def desc64(self) -> np.ndarray:
        if self._desc64 is None:
            self._desc64 = desc_u64(self.desc)
        return self._desc64


@dataclass
class Frame(KeypointSet):
    index: int
    uv: np.ndarray
    octave: np.ndarray
    angle: np.ndarray
    desc: np.ndarray
    u_right: np.ndarray
    depth: np.ndarray
    calib: StereoCalibration
    T_cw: np.ndarray | None = None
    point_ids: np.ndarray = field(default=None)  # type: ignore[assignment]
    match_xyz: np.ndarray = field(default=None)  # type: ignore[assignment]
    outlier: np.ndarray = field(default=None)  # type: ignore[assignment]
    # the keypoints whose matches the last pose optimization rejected (the viewer shows them)
    rejected: np.ndarray = field(default=None)  # type: ignore[assignment]
    _grid: KeypointGrid | None = None
    _desc64: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.uv)
        if self.point_ids is None:
            self.point_ids = np.full(n, -1, np.int64)
        if self.match_xyz is None:
            self.match_xyz = np.full((n, 3), np.nan)
        if self.outlier is None:
            self.outlier = np.zeros(n, bool)
        if self.rejected is None:
            self.rejected = np.zeros(0, np.int64)

    @classmethod
    def from_features(
        cls, index: int, feats: Features, u_right: np.ndarray, depth: np.ndarray, calib: StereoCalibration
    ) -> "Frame":
        return cls(index, feats.uv, feats.octave, feats.angle, feats.desc, u_right, depth, calib)


    @property
    def matched(self) -> np.ndarray:
        return np.isfinite(self.match_xyz[:, 0])

    @property
    def T_wc(self) -> np.ndarray:
        return inv_T(self.T_cw)

    def unproject(self, idx: np.ndarray, T_cw: np.ndarray | None = None) -> np.ndarray:
        """World positions of keypoints ``idx`` from their stereo depth."""
        T = self.T_cw if T_cw is None else T_cw
        K = self.calib.K
        z = self.depth[idx]
        x = (self.uv[idx, 0] - K[0, 2]) * z / K[0, 0]
        y = (self.uv[idx, 1] - K[1, 2]) * z / K[1, 1]
        Xc = np.stack([x, y, z], axis=1)
        return (Xc - T[:3, 3]) @ T[:3, :3]  # R^T (Xc - t), row-wise

    def clear_matches(self, sel: np.ndarray) -> None:
        self.point_ids[sel] = -1
        self.match_xyz[sel] = np.nan
        self.outlier[sel] = False
