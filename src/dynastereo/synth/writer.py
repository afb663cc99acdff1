"""``generate``: render a scenario into a KITTI-odometry-style folder with exact ground truth.

Layout (rooted at ``out``)::

    sequences/00/image_0/NNNNNN.png      left, 8-bit grey
    sequences/00/image_1/NNNNNN.png      right
    sequences/00/calib.txt               P0..P3 (P1/P3 carry -fx*baseline), KITTI format
    sequences/00/times.txt               10 Hz
    sequences/00/gt/disparity/NNNNNN.png left disparity, uint16 = disparity*256, 0 = no surface (sky)
    sequences/00/gt/masks/left/NNNNNN.png   uint8 instance id, 0 = none
    sequences/00/gt/masks/right/NNNNNN.png
    sequences/00/gt/objects.json         per frame and visible object: id, label, boxes, 3-D pose, ...
    poses/00.txt                         left camera-to-world 3x4 per frame, world = first camera

Coordinates in ``poses/00.txt`` and ``objects.json`` are KITTI's: camera x right, y down,
z forward; the world frame is the first left camera.
"""

from __future__ import annotations

import json
import math
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
from scipy import ndimage

from ..errors import InputError
from .objects import rot_y
from .render import PosedObject, Renderer, View
from .scenarios import SCENARIOS, Plan, make_plan
from .world import WorldParams, build_world

KITTI_FX = 718.856
KITTI_WIDTH = 1241
BASELINE = 0.54
DEFAULT_SIZE = (640, 192)
DEFAULT_NOISE = 1.5
OBJECTS_VERSION = 1
MOVING_SPEED = 0.05  # m/s: an object faster than this in a frame is "moving" there


def intrinsics(size: tuple[int, int]) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) for an image size: KITTI's focal length scaled to the width."""
    w, h = size
    f = KITTI_FX * w / KITTI_WIDTH
    return f, f, w / 2.0, h / 2.0


def parse_size(text: str | tuple[int, int]) -> tuple[int, int]:
    """``"640x192"`` -> (640, 192); raises InputError on anything else."""
    if isinstance(text, tuple):
        w, h = text
    else:
        parts = str(text).lower().replace("*", "x").split("x")
        try:
            w, h = (int(v) for v in parts)
        except ValueError:
            raise InputError(f"--size must be WIDTHxHEIGHT (e.g. 640x192), got {text!r}") from None
    if not (32 <= w <= 4096 and 16 <= h <= 4096):
        raise InputError(f"--size {w}x{h} out of range (32..4096 x 16..4096)")
    return int(w), int(h)


def _check_scenario(name: str) -> None:
    if name not in SCENARIOS:
        raise InputError(f"unknown scenario {name!r}; available: {', '.join(SCENARIOS)}")


#: The most frames ``generate`` renders (``--frames``): about 3 hours at 10 Hz.
MAX_FRAMES = 100_000


def check_options(scenario: str, frames: int | None, size: str | tuple[int, int]) -> tuple[int, int]:
    """``generate``'s options checked before anything is written (InputError naming the
    option): a known scenario, ``frames`` in 1..MAX_FRAMES, the size in range; the size."""
    _check_scenario(scenario)
    wh = parse_size(size)
    if frames is not None and not 1 <= int(frames) <= MAX_FRAMES:
        raise InputError(f"--frames must be in 1..{MAX_FRAMES}, got {frames}")
    return wh


def _pose_matrix(x: float, z: float, heading: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rot_y(heading)
    T[:3, 3] = (x, 0.0, z)
    return T


def _posed(plan: Plan, t: float, ground_y: float) -> list[PosedObject]:
    out = []
    for ob in plan.objects:
        R, o, ph = ob.pose(t, ground_y)
        out.append(PosedObject(ob.id, ob.shape, R, o, ph))
    return out


def _to_uint8(view: View, noise: float, rng: np.random.Generator | None) -> np.ndarray:
    img = view.image
    if rng is not None and noise > 0:
        img = img + rng.standard_normal(img.shape, dtype=np.float32) * np.float32(noise)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _disparity_png(view: View, bf: float) -> np.ndarray:
    with np.errstate(divide="ignore"):
        d = np.float32(bf) / view.depth
    d = np.where(np.isfinite(view.depth), d, 0.0)
    return np.clip(np.rint(d * 256.0), 0, 65535).astype(np.uint16)


def _boxes(ids: np.ndarray) -> tuple[list[tuple[int, int, int, int] | None], np.ndarray]:
    counts = np.bincount(ids.ravel(), minlength=256)
    slices = ndimage.find_objects(ids, max_label=255)
    boxes: list[tuple[int, int, int, int] | None] = [None] * 256
    for k, sl in enumerate(slices, start=1):
        if sl is not None:
            boxes[k] = (sl[1].start, sl[0].start, sl[1].stop, sl[0].stop)
    return boxes, counts


def _r(v: float, n: int = 4) -> float:
    return round(float(v), n)


def generate(
    out: str | Path,
    scenario: str,
    frames: int | None = None,
    seed: int = 0,
    size: tuple[int, int] | str = DEFAULT_SIZE,
    noise: float = DEFAULT_NOISE,
    progress: Callable[[int, int], None] | None = None,
    threads: int = 2,
) -> Path:
    """Render ``scenario`` into a KITTI-odometry folder under ``out``; returns ``out/sequences/00``.

    ``frames=None`` uses the scenario's default length (``loop``: one lap and 60 m);
    ``noise`` is the standard deviation of Gaussian grey-level noise added to the images
    (0 = noise-free: the right image is exactly the left one warped by the disparity);
    ``progress(done, total)`` is called after every frame; ``threads`` > 1 renders the two
    views and writes the PNGs in worker threads (same output).
    """
    W, H = check_options(scenario, frames, size)
    if not noise >= 0:
        raise InputError(f"noise must be >= 0, got {noise}")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("output exists and is not a folder", out)
    seq = out / "sequences" / "00"
    _clean_dirs(out, seq)

    world = build_world(seed, WorldParams())
    plan = make_plan(world, scenario, frames, seed)
    n = plan.frames
    fx, fy, cx, cy = intrinsics((W, H))
    renderer = Renderer(world, W, H, fx, fy, cx, cy)
    renderer.prepare([ob.shape for ob in plan.objects])

    T0inv = None
    poses: list[np.ndarray] = []
    frame_records: list[dict[str, Any]] = []
    with _PngWriter(threads) as writer:
        for i in range(n):
            x, z, th = plan.camera(i)
            t = i * plan.dt
            objs = _posed(plan, t, world.params.cam_height)
            left, right = _render_stereo(renderer, writer.pool, x, z, th, objs)
            nrng = np.random.default_rng([seed, 3, i]) if noise > 0 else None
            name = f"{i:06d}.png"
            writer.submit(seq / "image_0" / name, _to_uint8(left, noise, nrng))
            writer.submit(seq / "image_1" / name, _to_uint8(right, noise, nrng))
            writer.submit(seq / "gt" / "disparity" / name, _disparity_png(left, fx * BASELINE))
            writer.submit(seq / "gt" / "masks" / "left" / name, left.ids)
            writer.submit(seq / "gt" / "masks" / "right" / name, right.ids)

            Tw = _pose_matrix(x, z, th)
            if T0inv is None:
                T0inv = np.linalg.inv(Tw)
            poses.append((T0inv @ Tw)[:3, :4])
            recs = _object_records(plan, objs, t, left.ids, right.ids, T0inv, np.linalg.inv(Tw))
            frame_records.append({"index": i, "timestamp": _r(t, 6), "objects": recs})
            writer.throttle()
            if progress is not None:
                progress(i + 1, n)

    _write_text_files(out, seq, poses, n, plan.dt, (fx, fy, cx, cy))
    meta = _objects_meta(scenario, seed, n, (W, H), noise, plan, (fx, fy, cx, cy), world.params.cam_height)
    meta["frames_gt"] = frame_records
    with open(seq / "gt" / "objects.json", "w") as fh:
        json.dump(meta, fh, separators=(",", ":"))
    return seq


def _clean_dirs(out: Path, seq: Path) -> None:
    """Create the layout's folders; a previous, longer run must not leave frames behind."""
    dirs = [seq / "image_0", seq / "image_1", seq / "gt" / "disparity", seq / "gt" / "masks" / "left", seq / "gt" / "masks" / "right", out / "poses"]
    for d in dirs:
        d.mkdir(parents=True, exist_ok=True)
        for old in d.glob("*.png"):
            old.unlink()


class _PngWriter:
    """PNG writes, in worker threads when ``threads`` > 1 (at most ~64 pending); a
    context manager that waits for them all (and raises the first failure)."""

    def __init__(self, threads: int) -> None:
        self.pool = ThreadPoolExecutor(max_workers=max(1, threads)) if threads > 1 else None
        self.pending: list[Future] = []
        self.params = [cv2.IMWRITE_PNG_COMPRESSION, 1]

    def write(self, path: Path, arr: np.ndarray) -> None:
        ok, buf = cv2.imencode(path.suffix or ".png", arr, self.params)
        if not ok:
            raise InputError("cannot encode image", path)
        from ..io.outputs import write_bytes

        write_bytes(path, buf.tobytes())  # a failed write: OutputError naming the file

    def submit(self, path: Path, arr: np.ndarray) -> None:
        if self.pool is None:
            self.write(path, arr)
        else:
            self.pending.append(self.pool.submit(self.write, path, arr))

    def throttle(self) -> None:
        if len(self.pending) > 64:
            for f in self.pending[:-32]:
                f.result()
            self.pending = self.pending[-32:]

    def __enter__(self) -> "_PngWriter":
        return self

    def __exit__(self, exc_type, *exc: object) -> None:
        try:
            if exc_type is None:
                for f in self.pending:
                    f.result()
        finally:
            if self.pool is not None:
                self.pool.shutdown(wait=True)


def _render_stereo(renderer: Renderer, pool: ThreadPoolExecutor | None, x: float, z: float, th: float,
                   objs: list[PosedObject]) -> tuple[View, View]:
    """Left and right views of the rig whose left camera is at (x, z) with heading
    ``th``; texture filtering seen from the rig centre.  With a pool the left view
    renders in a worker while this thread renders the right one."""
    rx, rz = math.cos(th), -math.sin(th)
    mid = (x + 0.5 * BASELINE * rx, z + 0.5 * BASELINE * rz)  # texture filtering seen from the rig centre
    if pool is not None:
        fl = pool.submit(renderer.render, x, z, th, objs, mid)
        right = renderer.render(x + BASELINE * rx, z + BASELINE * rz, th, objs, mid)
        return fl.result(), right
    left = renderer.render(x, z, th, objs, mid)
    right = renderer.render(x + BASELINE * rx, z + BASELINE * rz, th, objs, mid)
    return left, right


def _object_records(plan: Plan, objs: list[PosedObject], t: float, ids_left: np.ndarray, ids_right: np.ndarray,
                    T0inv: np.ndarray, Tcam_inv: np.ndarray) -> list[dict[str, Any]]:
    """``objects.json`` records of the objects visible in one frame (module doc)."""
    bl, cl = _boxes(ids_left)
    br, cr = _boxes(ids_right)
    recs = []
    for ob, po in zip(plan.objects, objs):
        k = ob.id
        if cl[k] == 0 and cr[k] == 0:
            continue
        wdt, hgt, lng = ob.shape.size
        To = np.eye(4)
        To[:3, :3] = po.R
        To[:3, 3] = po.origin + po.R @ np.array([0.0, -hgt / 2, 0.0])  # centre of the box
        Tw_o = T0inv @ To
        pc = (Tcam_inv @ To)[:3, 3]
        speed = ob.motion.speed(t)
        moving = speed > MOVING_SPEED
        yaw = math.atan2(Tw_o[0, 2], Tw_o[2, 2])
        recs.append(
            {
                "id": k,
                "label": ob.label,
                "moving": bool(moving),
                "speed": _r(speed, 3),
                "box_left": list(bl[k]) if bl[k] else None,
                "box_right": list(br[k]) if br[k] else None,
                "pixels_left": int(cl[k]),
                "pixels_right": int(cr[k]),
                "position": [_r(v) for v in Tw_o[:3, 3]],
                "yaw": _r(yaw, 5),
                "pose": [_r(v, 6) for v in Tw_o[:3, :4].ravel()],
                "position_cam": [_r(v) for v in pc],
                "distance": _r(float(np.linalg.norm(pc)), 3),
            }
        )
    return recs


def _write_text_files(out: Path, seq: Path, poses: list[np.ndarray], n: int, dt: float,
                      K: tuple[float, float, float, float]) -> None:
    """``poses/00.txt``, ``times.txt`` and ``calib.txt`` (KITTI formats)."""
    fx, fy, cx, cy = K
    with open(out / "poses" / "00.txt", "w") as fh:
        for P in poses:
            fh.write(" ".join(f"{v:.9e}" for v in P.ravel()) + "\n")
    with open(seq / "times.txt", "w") as fh:
        for i in range(n):
            fh.write(f"{i * dt:.6e}\n")
    P0 = np.array([[fx, 0, cx, 0], [0, fy, cy, 0], [0, 0, 1, 0]], float)
    P1 = P0.copy()
    P1[0, 3] = -fx * BASELINE
    with open(seq / "calib.txt", "w") as fh:
        for name, P in (("P0", P0), ("P1", P1), ("P2", P0), ("P3", P1)):
            fh.write(f"{name}: " + " ".join(f"{v:.12e}" for v in P.ravel()) + "\n")


def _objects_meta(scenario: str, seed: int, n: int, size: tuple[int, int], noise: float, plan: Plan,
                  K: tuple[float, float, float, float], cam_height: float) -> dict[str, Any]:
    """The header of ``objects.json``: the run, the calibration, the conventions and the
    objects (``frames_gt`` is added by the caller)."""
    fx, fy, cx, cy = K
    return {
        "version": OBJECTS_VERSION,
        "generator": "dynastereo.synth",
        "scenario": scenario,
        "description": SCENARIOS[scenario].description,
        "seed": int(seed),
        "frames": n,
        "size": list(size),
        "noise": float(noise),
        "fps": 1.0 / plan.dt,
        "calibration": {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "baseline": BASELINE},
        "camera_height": cam_height,
        "conventions": {
            "frame": "KITTI camera: x right, y down, z forward; world = first left camera",
            "box": "x1, y1, x2, y2 in pixels, x2/y2 exclusive; visible pixels of the instance mask",
            "position": "centre of the object's 3-D bounding box, world frame",
            "pose": "3x4 object-to-world, row-major; object x right, y down, z forward; origin = box centre",
            "yaw": "heading about the world y axis, radians (0 = world +z)",
            "distance": "metres from the left camera centre to the box centre",
            "masks": "uint8 instance id = 'id', 0 = no object",
            "disparity": "uint16 = disparity*256 of the left view, 0 = no surface",
        },
        "objects": [
            {
                "id": ob.id,
                "label": ob.label,
                "size": [_r(v, 3) for v in ob.shape.size],
                "moves": bool(ob.motion.moves_between(0.0, (n - 1) * plan.dt)),
            }
            for ob in plan.objects
        ],
    }
