"""The dense, mover-free mesh of the static world: keyframes in, a triangle mesh out.

:class:`KeyframeRecorder` keeps, for each keyframe tracked, its stereo pair and the mask of
what must stay out of the map: every object judged moving or not yet judged in that frame
(the masks SLAM got) and every object whose track was judged moving at any frame of the
run (a car that was still when first seen and drove off later).  It keeps references, no
copies: the frame loop pays nothing.  Parked cars stay, as part of the street.

:func:`fuse` runs once the poses are final (after the last BA and any loop closure): per
keyframe the full-frame disparity (the ``stereo`` matcher; ``mesh.confidence`` as its
uniqueness margin), the movers' masks grown by ``mesh.mask_margin`` (and, within
``mesh.bleed_margin`` of them, the pixels at the depth of the mover beside them: its disparity
bled over the background), pixels on disparity
edges (``mesh.max_step``) and outside ``[min_depth, max_depth]`` dropped, the rig's
disparity offset (the SLAM's self-calibration) applied; then TSDF fusion at the final
keyframe poses and marching cubes (:mod:`.tsdf`).  World frame: the first camera's, as
the trajectory.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ..config import Config, MeshConfig
from ..datatypes import StereoCalibration, StereoMasks
from .tsdf import Mesh, TSDFVolume

log = logging.getLogger("dynastereo.mesh")


@dataclass
class KeyframeView:
    """One keyframe's inputs to the fusion: its images, what to leave out."""

    position: int  # in the order fed (the trajectory's row)
    left: np.ndarray  # grey or BGR: the colour
    right: np.ndarray
    mask: np.ndarray | None  # uint8 255 = a mover (moving or not yet judged): left out
    labels: np.ndarray | None = None  # int32 instance labels (k + 1 = tracks[k]), for the run's movers
    tracks: np.ndarray | None = None  # int64 track id per object


@dataclass
class MeshStats:
    """What the fusion did (run.json's ``mesh`` entry, the log line)."""

    keyframes: int = 0
    vertices: int = 0
    triangles: int = 0
    blocks: int = 0
    voxel_bytes: int = 0  # the voxel grid's peak memory
    disparity_s: float = 0.0  # CPU seconds
    fusion_s: float = 0.0
    marching_s: float = 0.0
    masked: bool = True
    compare_s: float = 0.0  # the unmasked comparison's fusion and marching cubes (mesh.compare)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        for k in ("disparity_s", "fusion_s", "marching_s", "compare_s"):
            d[k] = round(d[k], 3)
        return d


@dataclass
class DenseResult:
    mesh: Mesh
    stats: MeshStats
    unmasked: Mesh | None = None  # the same keyframes fused with the masks ignored (compare)


class KeyframeRecorder:
    """The keyframes of a run and the tracks judged moving (module doc)."""

    def __init__(self) -> None:
        self.views: list[KeyframeView] = []
        self.moving_tracks: set[int] = set()

    def add(self, position: int, left: np.ndarray, right: np.ndarray, masks: StereoMasks | None,
            slam_masks: StereoMasks | None, keyframe: bool) -> None:
        """One frame: the movers' track ids from its verdicts; its images when a keyframe."""
        objs = masks.objects if masks is not None else []
        self.moving_tracks.update(o.track_id for o in objs if o.moving and o.track_id >= 0)
        if not keyframe:
            return
        tracks = np.array([o.track_id for o in objs], np.int64) if objs else None
        labels = masks.labels_left if masks is not None and tracks is not None else None
        self.views.append(KeyframeView(position, left, right, None if slam_masks is None else slam_masks.left,
                                       labels, tracks))

    def __len__(self) -> int:
        return len(self.views)

    def leave_out(self, view: KeyframeView) -> np.ndarray | None:
        """The pixels of ``view`` kept out of the map: its movers' mask, plus the objects of
        tracks judged moving at any frame (None: nothing)."""
        mask = view.mask
        if view.labels is None or view.tracks is None or not self.moving_tracks:
            return mask
        ever = np.isin(view.tracks, np.fromiter(self.moving_tracks, np.int64))
        if not ever.any():
            return mask
        lut = np.zeros(len(view.tracks) + 1, bool)
        lut[1:] = ever
        extra = lut[np.clip(view.labels, 0, len(view.tracks))]
        out = np.zeros(view.labels.shape, np.uint8) if mask is None else mask.copy()
        out[extra] = 255
        return out


def downscale(img: np.ndarray, scale: int) -> np.ndarray:
    if scale == 1:
        return img
    h, w = img.shape[:2]
    return cv2.resize(img, (w // scale, h // scale), interpolation=cv2.INTER_AREA)


def scaled_K(K: np.ndarray, scale: int) -> np.ndarray:
    """The intrinsics of an image downscaled by ``scale`` (pixel centres kept)."""
    Ks = np.array(K, np.float64)
    Ks[0, 0] /= scale
    Ks[1, 1] /= scale
    Ks[0, 2] = (K[0, 2] + 0.5) / scale - 0.5
    Ks[1, 2] = (K[1, 2] + 0.5) / scale - 0.5
    return Ks


BLEED_DEPTH = 1.0  # m: a pixel in a mover's bleed ring this near its depth is taken for the mover


def _grow(m: np.ndarray, r: float) -> np.ndarray:
    r = int(round(r))
    if r <= 0:
        return m
    return cv2.dilate(m.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))) > 0


def disparity_edges(d: np.ndarray, max_step: float) -> np.ndarray:
    """Pixels next to a disparity jump: a second difference (across or along the rows)
    above ``max_step`` -- zero on any plane, whatever its slant (a road's disparity
    changes every row), the size of the jump at an object's border."""
    edge = np.zeros(d.shape, bool)
    valid = d > 0
    for axis in (0, 1):
        a = np.moveaxis(d, axis, 0)
        ok = np.moveaxis(valid, axis, 0)
        sec = np.abs(a[:-2] + a[2:] - 2.0 * a[1:-1])
        bad = (sec > max_step) & ok[:-2] & ok[2:] & ok[1:-1]
        jump = np.moveaxis(edge, axis, 0)
        jump[1:-1] |= bad
        jump[:-2] |= bad
        jump[2:] |= bad
    return edge


def keyframe_depth(view: KeyframeView, mask: np.ndarray | None, calib: StereoCalibration, matcher: Any,
                   cfg: MeshConfig, disparity_offset: float = 0.0) -> np.ndarray:
    """Depth (float32 m, 0 = none) of the keyframe's static pixels at 1/``cfg.scale`` of
    the image's resolution (module doc)."""
    z, m = depth_and_movers(view, mask, calib, matcher, cfg, disparity_offset)
    if m is not None:
        z[m] = 0.0
    return z


def depth_and_movers(view: KeyframeView, mask: np.ndarray | None, calib: StereoCalibration, matcher: Any,
                     cfg: MeshConfig, disparity_offset: float = 0.0) -> tuple[np.ndarray, np.ndarray | None]:
    """(depth of every pixel, the movers' pixels grown by the margin or None) at
    1/``cfg.scale`` resolution: :func:`keyframe_depth` before the mask is applied."""
    s = int(cfg.scale)
    lg = view.left if view.left.ndim == 2 else cv2.cvtColor(view.left, cv2.COLOR_BGR2GRAY)
    rg = view.right if view.right.ndim == 2 else cv2.cvtColor(view.right, cv2.COLOR_BGR2GRAY)
    d = matcher.compute(downscale(lg, s), downscale(rg, s)) * np.float32(s)  # full-resolution pixels
    valid = d > 0
    # the left border, where the right image may not hold the match at all (the matcher's
    # disparity range): a wrong match there is not told from a right one
    valid[:, :matcher.cfg.num_disparities] = False
    d[valid] += np.float32(disparity_offset)
    valid &= ~disparity_edges(np.where(valid, d, 0), cfg.max_step)
    with np.errstate(divide="ignore"):
        z = np.where(valid & (d > 0), calib.bf / np.maximum(d, 1e-6), 0.0).astype(np.float32)
    m = None
    if mask is not None and mask.any():
        m0 = downscale((mask > 0).astype(np.uint8) * 255, s) > 0
        m = _grow(m0, cfg.mask_margin / s)
        rb = int(round(cfg.bleed_margin / s))
        if rb > 0:
            # the ring where the movers' disparity may bleed: a pixel there at the depth of
            # the nearest mover beside it (+- BLEED_DEPTH) is the mover smeared, not what lies
            # behind it (farther) or the road before it (nearer)
            near = cv2.dilate(np.where(m0 & valid, d, 0.0).astype(np.float32),
                              cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rb + 1, 2 * rb + 1)))
            with np.errstate(divide="ignore"):
                z_near = np.where(near > 0, calib.bf / np.maximum(near, 1e-6), 0.0)
            m |= (near > 0) & (z > 0) & (np.abs(z - z_near) <= BLEED_DEPTH)
    z[(z < cfg.min_depth) | (z > cfg.max_depth)] = 0.0
    return z, m


def mesh_matcher(config: Config):
    """The stereo matcher of the mesh, for images downscaled by ``mesh.scale``:
    ``mesh.algorithm`` / ``block_size`` (SGBM's P1 / P2 from the block), the disparity
    range shrunk with the images, ``mesh.confidence`` its uniqueness margin, the other
    settings from ``stereo``."""
    from ..config import StereoConfig
    from ..masking.disparity import StereoMatcher

    m, s = config.mesh, int(config.mesh.scale)
    nd = max(16, -(-config.stereo.num_disparities // (16 * s)) * 16)
    st = dataclasses.replace(config.stereo, algorithm=m.algorithm, block_size=m.block_size, p1=None, p2=None,
                             uniqueness_ratio=int(m.confidence), region="full", wls=False, scale=1,
                             num_disparities=nd, min_disparity=config.stereo.min_disparity // s,
                             speckle_window_size=config.stereo.speckle_window_size // (s * s))
    return StereoMatcher(StereoConfig(**dataclasses.asdict(st)))


def fuse(recorder: KeyframeRecorder, poses: np.ndarray, calib: StereoCalibration, config: Config, *,
         disparity_offset: float = 0.0, masked: bool = True, ok: np.ndarray | None = None,
         compare: bool = False) -> DenseResult:
    """The mesh of ``recorder``'s keyframes at ``poses`` ((N, 3, 4) camera-to-world, one per
    frame fed: ``System.trajectory()``), module doc.  ``masked`` False: the movers are fused
    too; ``compare``: both, the unmasked one in ``result.unmasked`` (the same disparity,
    fused twice); ``ok``: per frame, whether it was tracked (lost frames' predicted poses
    are not fused)."""
    cfg = config.mesh
    stats = MeshStats(masked=masked)
    vol = TSDFVolume(cfg.voxel_size, cfg.truncation, cfg.min_weight)
    both = TSDFVolume(cfg.voxel_size, cfg.truncation, cfg.min_weight) if compare else None
    matcher = mesh_matcher(config)
    K = scaled_K(calib.K, cfg.scale)
    compare_s = 0.0
    for view in recorder.views:
        if view.position >= len(poses) or (ok is not None and not ok[view.position]):
            continue
        t0 = time.process_time()
        z, movers = depth_and_movers(view, recorder.leave_out(view) if (masked or compare) else None, calib,
                                     matcher, cfg, disparity_offset)
        img = downscale(view.left, cfg.scale)
        pose = np.asarray(poses[view.position], np.float64)
        t1 = time.process_time()
        if both is not None:
            both.integrate(z, img, K, pose)
        t2 = time.process_time()
        if masked and movers is not None:
            z[movers] = 0.0
        vol.integrate(z, img, K, pose)
        t3 = time.process_time()
        stats.disparity_s += t1 - t0
        stats.fusion_s += t3 - t2
        compare_s += t2 - t1
        stats.keyframes += 1
    t0 = time.process_time()
    mesh = vol.mesh()
    stats.marching_s = time.process_time() - t0
    stats.vertices, stats.triangles = len(mesh.vertices), len(mesh.faces)
    stats.blocks, stats.voxel_bytes = vol.n_blocks, vol.peak_bytes
    unmasked = None
    if both is not None:
        t0 = time.process_time()
        unmasked = both.mesh()
        stats.compare_s = compare_s + time.process_time() - t0
    return DenseResult(mesh, stats, unmasked)


def fuse_system(recorder: KeyframeRecorder, system: Any, calib: StereoCalibration, config: Config, *,
                masked: bool = True) -> DenseResult:
    """:func:`fuse` at a SLAM system's final poses (after its shutdown: the last BA done);
    the unmasked comparison too with ``mesh.compare``."""
    poses = system.trajectory()
    ok = np.array([str(s.status) in ("tracked", "init") for s in system.results()], bool)
    return fuse(recorder, poses, calib, config, disparity_offset=float(system.disparity_offset), masked=masked,
                ok=ok, compare=bool(config.mesh.compare))


__all__ = ["KeyframeRecorder", "KeyframeView", "MeshStats", "DenseResult", "fuse", "fuse_system", "keyframe_depth",
           "mesh_matcher"]
