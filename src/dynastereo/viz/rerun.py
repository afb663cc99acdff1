"""The rerun viewer (https://rerun.io) as a frame observer: live (``--viewer``) or
recorded to an ``.rrd`` file (``--rrd FILE``, headless).

Needs the optional extra ``pip install dynastereo[viz]`` (``rerun-sdk``); imported only
when a viewer or a recording is asked for.  Entities, on the timeline ``frame`` (the
position in the order fed) and ``time`` (the sequence's timestamps, seconds):

====================================  =====================================================
``world/camera``                      the left camera's pose (``Transform3D``) and a
                                      ``Pinhole`` frustum (RDF: x right, y down, z forward)
``world/camera/image``                the left image, seen through the frustum
``world/trajectory``                  the estimated camera path so far (``LineStrips3D``)
``world/ground_truth``                the ground truth (``--gt``), logged once, static
``world/local_map``                   the local map's points (``Points3D``)
``world/objects``                     the objects' 3-D boxes (``Boxes3D``, ``label #id speed``),
                                      moving red, static green, undecided orange
``world/object_paths``                each object's path in the world so far (``LineStrips3D``)
``camera/left``, ``camera/right``     the images
``camera/left/mask``,                 the dynamic masks (``SegmentationImage``: 1 = masked)
``camera/right/mask``
``camera/left/boxes``                 the objects' boxes, ``label #track_id method``
``camera/left/features``              tracked keypoints: green inliers, red outliers
``camera/disparity``                  the masker's full-frame disparity (when computed)
``timing/<stage>``                    milliseconds per stage (``Scalars``)
``status``                            tracking status per frame (``TextLog``)
====================================  =====================================================
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import DynastereoError
from ..observers import FrameEvent

MASK_CLASS = 1  # SegmentationImage class of the masked pixels
INLIER_COLOR = (40, 220, 40)
OUTLIER_COLOR = (230, 40, 40)
TRAJECTORY_COLOR = (30, 120, 255)
GT_COLOR = (150, 150, 150)


def _import_rerun():
    try:
        import rerun as rr
    except ImportError:
        raise DynastereoError(
            "the rerun viewer needs the optional extra: pip install 'dynastereo[viz]' (rerun-sdk)"
        ) from None
    return rr


class RerunObserver:
    """Logs every frame of a job to rerun.  ``spawn``: start the viewer and stream to it;
    ``rrd``: write a recording file (both may be given).  ``gt``: the ground-truth
    trajectory's positions (N, 3), drawn once."""

    def __init__(self, *, spawn: bool = False, rrd: str | Path | None = None, gt: np.ndarray | None = None,
                 name: str = "dynastereo") -> None:
        if not spawn and rrd is None:
            raise ValueError("RerunObserver: give spawn=True and/or rrd=FILE")
        rr = _import_rerun()
        self.rr = rr
        self.rec = rr.RecordingStream(application_id="dynastereo", recording_id=None)
        self.rec.send_recording_name(name)
        sinks = []
        if rrd is not None:
            Path(rrd).parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(rrd)))
        if spawn:
            self.rec.spawn(connect=False)  # the viewer process, listening on the default port
            sinks.append(rr.GrpcSink())
        self.rec.set_sinks(*sinks)
        self._positions: list[np.ndarray] = []
        self._paths = None  # objects.world.ObjectPaths, made at the first object
        self._static_done = False
        self._gt = gt

    def _log_static(self, event: FrameEvent) -> None:
        rr, rec = self.rr, self.rec
        rec.log("world", rr.ViewCoordinates.RDF, static=True)  # camera coordinates of the first frame
        rec.log("camera/left/mask", rr.AnnotationContext([(0, "static", (0, 0, 0, 0)),
                                                          (MASK_CLASS, "masked", (255, 0, 0, 140))]), static=True)
        rec.log("camera/right/mask", rr.AnnotationContext([(0, "static", (0, 0, 0, 0)),
                                                           (MASK_CLASS, "masked", (255, 0, 0, 140))]), static=True)
        c = event.calibration
        if c is not None:
            rec.log("world/camera", rr.Pinhole(image_from_camera=c.K, width=c.width, height=c.height,
                                               camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=1.0),
                    static=True)
        if self._gt is not None:
            rec.log("world/ground_truth", rr.LineStrips3D([np.asarray(self._gt)], colors=[GT_COLOR]), static=True)
        self._static_done = True

    def on_frame(self, event: FrameEvent) -> None:
        rr, rec = self.rr, self.rec
        if not self._static_done:
            self._log_static(event)
        f = event.frame
        rec.set_time("frame", sequence=event.position)
        rec.set_time("time", duration=float(f.timestamp))
        rec.log("camera/left", rr.Image(f.left))
        rec.log("camera/right", rr.Image(f.right))
        m = event.masks
        if m is not None:
            rec.log("camera/left/mask", rr.SegmentationImage((m.left > 0).astype(np.uint8) * MASK_CLASS))
            rec.log("camera/right/mask", rr.SegmentationImage((m.right > 0).astype(np.uint8) * MASK_CLASS))
            if m.objects:
                boxes = np.array([o.box for o in m.objects], np.float32)
                labels = [f"{o.label} #{o.track_id} {o.method}" if o.track_id >= 0 else f"{o.label} {o.method}"
                          for o in m.objects]
                rec.log("camera/left/boxes", rr.Boxes2D(array=boxes, array_format=rr.Box2DFormat.XYXY, labels=labels,
                                                        class_ids=[abs(hash(o.label)) % 1000 for o in m.objects]))
            else:
                rec.log("camera/left/boxes", rr.Clear(recursive=False))
            if m.disparity is not None:
                rec.log("camera/disparity", rr.DepthImage(np.maximum(m.disparity, 0).astype(np.float32),
                                                          colormap="turbo"))
        for stage, ms in event.ms.items():
            rec.log(f"timing/{stage}", rr.Scalars(float(ms)))
        if event.pose is not None:
            self._log_pose(event)

    def _log_pose(self, event: FrameEvent) -> None:
        rr, rec = self.rr, self.rec
        T = np.asarray(event.pose, np.float64)
        rec.log("world/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        rec.log("world/camera/image", rr.Image(event.frame.left))
        self._positions.append(T[:3, 3].copy())
        rec.log("world/trajectory", rr.LineStrips3D([np.array(self._positions)], colors=[TRAJECTORY_COLOR]))
        rec.log("status", rr.TextLog(f"frame {event.frame.index}: {event.status}",
                                     level="WARN" if event.status == "lost" else "INFO"))
        self._log_objects(event)
        view = event.system.frame_view() if event.system is not None else None
        if view is None:
            return
        uv = np.concatenate([view.uv[view.inlier], view.uv[view.outlier]])
        colors = [INLIER_COLOR] * int(view.inlier.sum()) + [OUTLIER_COLOR] * int(view.outlier.sum())
        rec.log("camera/left/features", rr.Points2D(uv, colors=colors, radii=1.5))
        rec.log("world/local_map", rr.Points3D(view.local_points, colors=[(200, 200, 200)], radii=0.03))

    def _log_objects(self, event: FrameEvent) -> None:
        """The objects' boxes in the world and their paths (``objects.world``)."""
        from ..objects.world import ObjectPaths, verdict_rgb

        rr, rec = self.rr, self.rec
        objs = [o for o in (event.masks.objects if event.masks is not None else []) if o.world is not None]
        if not objs:
            rec.log("world/objects", rr.Clear(recursive=False))
            return
        centres, halves, quats, colours, labels = [], [], [], [], []
        for o in objs:
            s = o.world
            h = np.array([s.heading[0], 0.0, s.heading[2]])
            yaw = float(np.arctan2(h[0], h[2]))  # about y (down): z -> the heading
            centres.append(s.world)
            halves.append(0.5 * np.asarray(s.extent))
            quats.append((0.0, np.sin(yaw / 2), 0.0, np.cos(yaw / 2)))
            colours.append(verdict_rgb(o.moving))
            sp = f" {s.speed:.1f} m/s" if s.speed is not None else ""
            labels.append(f"{o.label} #{o.track_id}{sp}")
        if self._paths is None:
            self._paths = ObjectPaths()
        self._paths.add(objs)
        rec.log("world/objects", rr.Boxes3D(centers=centres, half_sizes=halves,
                                            quaternions=[rr.Quaternion(xyzw=q) for q in quats],
                                            colors=colours, labels=labels))
        paths = self._paths.paths()
        if paths:
            rec.log("world/object_paths", rr.LineStrips3D([p for _, p, _ in paths],
                                                          colors=[verdict_rgb(v) for _, _, v in paths]))

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()


def recorded_entities(rrd: str | Path) -> dict[str, int]:
    """Entity path -> rows logged on the timelines (0: static only), of an ``.rrd``
    recording, read back with rerun's own reader (``rerun.chunk.RrdReader``)."""
    rr = _import_rerun()
    out: dict[str, int] = {}
    for c in rr.chunk.RrdReader(str(rrd)).stream():
        n = 0 if c.is_static else c.num_rows
        out[str(c.entity_path)] = out.get(str(c.entity_path), 0) + n
    return out
