"""One configuration object for the whole pipeline, loaded from YAML.

``Config`` is a tree of dataclasses; ``load_config(path)`` reads a YAML file whose
keys mirror the tree (unknown keys are an error naming the file and the key), and
``Config.with_overrides`` applies dotted ``section.key=value`` overrides (the CLI
uses them).  ``dump_config`` writes it back, so ``run.json`` can record what was used.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import cattrs
import cattrs.gen
import yaml

from .dotted import nest_dotted
from .yamlcheck import duplicate_key, yaml_error_line
from .errors import ConfigError
from .datatypes import DEFAULT_DYNAMIC_CLASSES


StereoAlgorithm = Literal["bm", "sgbm", "sgbm3way", "hh", "hh4"]
StereoRegion = Literal["full", "boxes"]
STEREO_ALGORITHMS: tuple[str, ...] = typing.get_args(StereoAlgorithm)
STEREO_REGIONS: tuple[str, ...] = typing.get_args(StereoRegion)
STEREO_SCALES = (1, 2, 4)


def _bad(key: str, want: str, got: Any) -> ConfigError:
    """``ConfigError("<key> must be <want>, got <got>")``."""
    return ConfigError(f"{key} must be {want}, got {got!r}")


@dataclass
class StereoConfig:
    """Disparity estimation (thesis 3.3.1/3.3.2): OpenCV StereoBM / StereoSGBM + WLS."""

    algorithm: StereoAlgorithm = "bm"  # bm: OpenCV StereoBM; sgbm, sgbm3way, hh, hh4: StereoSGBM in that mode
    min_disparity: int = 0  # smallest disparity searched, px
    num_disparities: int = 96  # multiple of 16
    block_size: int = 15  # odd; BM: 5..255, SGBM: 1..
    p1: int | None = None  # SGBM smoothness; None -> 8*cn*block_size^2
    p2: int | None = None  # None -> 32*cn*block_size^2
    disp12_max_diff: int = 1  # left-right consistency check, px (-1: off)
    pre_filter_cap: int = 31  # clip of the prefiltered image (BM: 1..63)
    uniqueness_ratio: int = 10  # % by which the best match must beat the second best
    speckle_window_size: int = 100  # largest speckle region removed, px (0: off)
    speckle_range: int = 2  # disparity variation within a connected region
    texture_threshold: int = 10  # BM only
    wls: bool = False  # smooth the disparity with the WLS filter (opencv-contrib)
    wls_lambda: float = 8000.0  # WLS smoothness weight
    wls_sigma: float = 1.5  # WLS edge sensitivity to the image
    # Where to compute disparity when only the masks need it:
    # "full" = whole frame; "boxes" = only the image band covering the detections.
    region: StereoRegion = "boxes"
    # Downscale factor for the masking disparity (1 = full resolution, 2 = half).  1 by
    # default: 2 (configs/fast.yaml) costs the masks' disparity a third to a quarter of the
    # CPU (4-5 ms a stereo pair on KITTI) with recall and IoU held, but the motion test's
    # verdicts on raw 0001's tram follow the disparity: ATE median x1.23 over twelve
    # n_features variants there (docs/guide/performance.md).
    scale: int = 1

    def __post_init__(self) -> None:
        self.validate()

    def default_p(self, cn: int = 1) -> tuple[int, int]:
        """SGBM's (P1, P2): the configured ones, else 8 / 32 * cn * block_size^2."""
        area = self.block_size * self.block_size
        return (8 * cn * area if self.p1 is None else int(self.p1), 32 * cn * area if self.p2 is None else int(self.p2))

    def validate(self) -> None:
        """Range checks (ConfigError naming the key); run whenever one is made or loaded."""
        alg = str(self.algorithm).lower()
        if alg not in STEREO_ALGORITHMS:
            raise _bad("stereo.algorithm", "one of " + ", ".join(STEREO_ALGORITHMS), self.algorithm)
        if self.num_disparities <= 0 or self.num_disparities % 16 != 0:
            raise _bad("stereo.num_disparities", "a positive multiple of 16", self.num_disparities)
        lo = 5 if alg == "bm" else 1
        if self.block_size % 2 != 1 or not (lo <= self.block_size <= 255):
            raise _bad("stereo.block_size", f"odd and in [{lo}, 255] for {alg}", self.block_size)
        if alg == "bm":
            if not (1 <= self.pre_filter_cap <= 63):
                raise _bad("stereo.pre_filter_cap", "in [1, 63] for bm", self.pre_filter_cap)
            if self.texture_threshold < 0:
                raise _bad("stereo.texture_threshold", ">= 0", self.texture_threshold)
        else:
            if self.pre_filter_cap < 1:
                raise _bad("stereo.pre_filter_cap", ">= 1", self.pre_filter_cap)
            p1, p2 = self.default_p()
            if p1 < 0 or p2 <= p1:
                raise ConfigError(f"stereo.p2 must be greater than stereo.p1 (>= 0), got p1={p1}, p2={p2}")
        if self.uniqueness_ratio < 0:
            raise _bad("stereo.uniqueness_ratio", ">= 0", self.uniqueness_ratio)
        if self.speckle_window_size < 0 or self.speckle_range < 0:
            raise ConfigError(
                "stereo.speckle_window_size and stereo.speckle_range must be >= 0, got "
                f"{self.speckle_window_size} and {self.speckle_range}"
            )
        if self.wls and not (self.wls_lambda > 0 and self.wls_sigma > 0):
            raise ConfigError(
                f"stereo.wls_lambda and stereo.wls_sigma must be > 0, got {self.wls_lambda} and {self.wls_sigma}"
            )
        if self.region not in STEREO_REGIONS:
            raise _bad("stereo.region", "one of " + ", ".join(STEREO_REGIONS), self.region)
        if self.scale not in STEREO_SCALES:
            raise _bad("stereo.scale", f"one of {STEREO_SCALES}", self.scale)


DetectorCanvas = Literal["frame", "tiles", "model"]
DetectorSchedule = Literal["every", "interval", "rotate"]
DetectorContrast = Literal["clahe", "none"]
DETECTOR_CANVASES: tuple[str, ...] = typing.get_args(DetectorCanvas)
DETECTOR_SCHEDULES: tuple[str, ...] = typing.get_args(DetectorSchedule)
DETECTOR_CONTRASTS: tuple[str, ...] = typing.get_args(DetectorContrast)
DetectorRuntime = Literal["auto", "onnxruntime", "openvino"]
DetectorPrecision = Literal["auto", "f32", "bf16"]
DETECTOR_RUNTIMES: tuple[str, ...] = typing.get_args(DetectorRuntime)
DETECTOR_PRECISIONS: tuple[str, ...] = typing.get_args(DetectorPrecision)


@dataclass
class DetectorConfig:
    """The detector and how it meets the frame (``masking/detection/stage.py``).

    The defaults are the row that wins ``benchmarks/bench_recall.py`` (docs/design/finding-objects.md): the frame at its own scale in a rectangular canvas, CLAHE contrast,
    the network on every other frame and the boxes carried by optical flow between runs.
    """

    name: str = "yolox-nano"  # registry name or a path to a .cfg / .onnx file
    score_threshold: float = 0.15  # detections scoring less are dropped
    nms_threshold: float = 0.45  # IoU above which non-maximum suppression merges boxes
    input_size: int | None = None  # canvas "model" only; None: the model's native size
    dynamic_classes: list[str] = field(default_factory=lambda: list(DEFAULT_DYNAMIC_CLASSES))  # COCO classes masked
    # inference threads: 2 halves the network's wall time (a live node's latency: 78 -> 64 ms
    # median, bench_ros_latency.py) for a few % more CPU a call; offline runs on two cores
    # keep their frame rate (bench_peers.py --against); the boxes are the same bit for bit
    threads: int = 2
    min_box_size: float = 4.0  # boxes thinner than this (pixels) are dropped
    # How the frame meets the network: "frame" = one canvas of the frame's aspect at
    # `scale` (the ONNX graph rewritten exactly / Darknet at a rectangular blob); "tiles" =
    # `tiles` overlapping tiles across the frame at `scale`, batched, boxes merged across
    # the seams; "model" = letterboxed into the model's own square canvas (shrinks a wide
    # frame: a KITTI frame to a third)
    canvas: DetectorCanvas = "frame"
    scale: float = 1.0  # the canvas's size relative to the frame (canvas frame / tiles)
    tiles: int = 3  # tiles across the frame (canvas tiles)
    tile_overlap: float = 0.2  # share of a tile's width overlapping each neighbour
    # canvas frame/tiles: the top fraction of the frame left out (sky).  0 by default: 0.25
    # costs the network a quarter less, but a tall near object (raw 0001's tram) is then
    # cut at the band and left half in the map: with configs/fast.yaml's settings, raw
    # 0001's ATE median x2.6 over eight n_features variants and 8 of its 10 movers masked
    # in time instead of 10 (docs/guide/performance.md)
    band_top: float = 0.0
    contrast: DetectorContrast = "clahe"  # the detector's input only
    # When the network runs: "every" frame, every `interval`-th frame ("interval"), or
    # one tile per frame in turn ("rotate", canvas "tiles"); boxes are carried between
    schedule: DetectorSchedule = "interval"
    interval: int = 2  # schedule interval: the network runs on every interval-th frame
    track: bool = True  # carry boxes between frames (optical flow), with track ids
    max_carry: int = 2  # detector runs a box is carried without a confirming detection
    # the carrying's optical flow on the image shrunk 1x or 2x: 1 by default -- 2 halves the
    # carrying's CPU (about 3.5 ms a stereo pair on KITTI) with the masks' recall and IoU
    # held, but one of raw 0001's 10 movers is then masked a frame late
    # (docs/guide/performance.md)
    carry_downscale: int = 1
    # The ONNX runtime (masking/detection/runtime.py): "auto" = OpenVINO in bf16 when it is
    # installed (the extra dynastereo[openvino]) and the CPU computes in bf16, else
    # onnxruntime f32; precision "auto" = bf16 where available (OpenVINO only), else f32.
    # Default onnxruntime: with auto, raw 0001's ATE rose (see band_top)
    runtime: DetectorRuntime = "onnxruntime"
    precision: DetectorPrecision = "auto"  # f32, bf16 (OpenVINO only) or auto (bf16 where available)
    # A grey frame runs a one-channel copy of the network (YOLOX: its first convolution's
    # weights summed over the three equal colour channels; rewrite.py "Grey input"): about
    # 10 % less network CPU; false = three equal channels
    grey_input: bool = True

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Range checks (ConfigError naming the key); run whenever one is made or loaded."""
        def bad(key: str, want: str, got: Any) -> ConfigError:
            return _bad(f"detector.{key}", want, got)

        if self.canvas not in DETECTOR_CANVASES:
            raise bad("canvas", "one of " + ", ".join(DETECTOR_CANVASES), self.canvas)
        if self.schedule not in DETECTOR_SCHEDULES:
            raise bad("schedule", "one of " + ", ".join(DETECTOR_SCHEDULES), self.schedule)
        if self.runtime not in DETECTOR_RUNTIMES:
            raise bad("runtime", "one of " + ", ".join(DETECTOR_RUNTIMES), self.runtime)
        if self.precision not in DETECTOR_PRECISIONS:
            raise bad("precision", "one of " + ", ".join(DETECTOR_PRECISIONS), self.precision)
        if self.contrast not in DETECTOR_CONTRASTS:
            raise bad("contrast", "one of " + ", ".join(DETECTOR_CONTRASTS), self.contrast)
        if not (0.1 <= self.scale <= 4.0):
            raise bad("scale", "in [0.1, 4]", self.scale)
        if self.tiles < 1:
            raise bad("tiles", ">= 1", self.tiles)
        if not (0.0 <= self.tile_overlap < 1.0):
            raise bad("tile_overlap", "in [0, 1)", self.tile_overlap)
        if not (0.0 <= self.band_top < 0.9):
            raise bad("band_top", "in [0, 0.9)", self.band_top)
        if self.interval < 1:
            raise bad("interval", ">= 1", self.interval)
        if self.max_carry < 0:
            raise bad("max_carry", ">= 0", self.max_carry)
        if self.carry_downscale not in (1, 2):
            raise bad("carry_downscale", "1 or 2", self.carry_downscale)
        if not isinstance(self.grey_input, bool):
            raise bad("grey_input", "true or false", self.grey_input)
        if not (0.0 <= self.score_threshold < 1.0):
            raise bad("score_threshold", "in [0, 1)", self.score_threshold)
        if not (0.0 < self.nms_threshold <= 1.0):
            raise bad("nms_threshold", "in (0, 1]", self.nms_threshold)
        if self.threads < 1:
            raise bad("threads", ">= 1", self.threads)
        if self.input_size is not None and self.input_size < 32:
            raise bad("input_size", ">= 32 (or null: the model's own)", self.input_size)
        if self.min_box_size < 0:
            raise bad("min_box_size", ">= 0", self.min_box_size)
        if self.schedule == "rotate" and self.canvas != "tiles":
            raise ConfigError("detector.schedule 'rotate' needs detector.canvas 'tiles' (one tile per frame)")
        if self.schedule != "every" and not self.track:
            raise ConfigError(f"detector.schedule {self.schedule!r} needs detector.track: true "
                              "(boxes are carried between the detector's runs)")


TransferMode = Literal["rigid", "affine"]
MaskerKind = Literal["outline", "box", "seg", "none"]
TRANSFER_MODES: tuple[str, ...] = typing.get_args(TransferMode)
MASKER_KINDS: tuple[str, ...] = typing.get_args(MaskerKind)


@dataclass
class OutlineConfig:
    """Outline from the dominant disparity peak inside each box (thesis 3.3.3)."""

    bin_width: float = 1.0  # histogram bin width in disparity pixels
    peak_tolerance: float = 1.5  # +- pixels (or relative, see below) around the peak
    peak_tolerance_rel: float = 0.08  # relative tolerance, for near objects
    min_valid_fraction: float = 0.05  # fewer valid pixels than this -> box fallback
    min_box_pixels: int = 64  # smaller boxes are masked whole
    min_box_side: int = 8  # boxes narrower or lower than this (px) are masked whole
    fill_holes: bool = True  # fill holes inside each outline
    dilate: int = 3  # dilation radius in pixels applied to each object mask
    keep_largest_component: bool = True  # keep only the largest connected part of an outline
    # Among histogram peaks at least this fraction of the highest, take the nearest
    # (largest disparity): the detected object stands in front of its background. 1 = off.
    near_peak_ratio: float = 0.5
    # Extend the peak over contiguous bins holding at least this fraction of its count
    # (slanted surfaces: a car seen from the side spans many disparities). 1 = off.
    peak_extend_ratio: float = 0.1
    # An outline covering less than this fraction of its box (the part no nearer object
    # takes) is a disparity failure (an object cut by the image border, a near one with
    # little texture): the box is masked. 0 = off.
    min_outline_fraction: float = 0.6
    # How a left mask moves to the right image: "affine" (d = a + b x + c y fitted per
    # object, rigid when the fit is poor) or "rigid" (shift by the object's disparity).
    transfer: TransferMode = "affine"
    # Carried boxes keep their outline (masking/maskers.py): a box carried from the previous
    # frame whose scale changed by at most carry_max_scale and whose centre moved by at most
    # carry_max_shift of its size, and whose disparity under the moved mask is still its
    # peak's (within the peak tolerance), gets its previous outline moved by the box's flow
    # (scale + shift) instead of a new one; the right mask follows by its disparity.
    carry_outline: bool = False
    carry_max_scale: float = 0.05  # carry_outline: largest change of a carried box's scale
    carry_max_shift: float = 0.25  # carry_outline: largest move of its centre, in box sizes
    # An object partly hidden behind a nearer one in the left image also gets, in the right
    # image, the band the right camera sees past the nearer object's right edge.
    transfer_occluded: bool = True
    # Histogram weight of pixels a box shares with other boxes (1 = off): a car's box
    # reaching over the truck in front of it must not take the truck's disparity peak.
    overlap_weight: float = 0.25
    # A box whose peak is a neighbouring box's and more than this fraction of whose
    # in-peak pixels lie at that box (inside or within a few pixels: the matcher spills a
    # near object's disparity past its edge) gives the peak up. 1 = off.
    claim_fraction: float = 0.5
    # Ground removal (masking/ground.py): the road's disparity is a line in the image
    # row, d = a v + c, fitted per frame (v-disparity Hough + least squares) to a coarse
    # disparity of the image's lower part; pixels less than ground_tolerance px above
    # it (measured, or filled along the row) are road and leave every object's mask.
    # docs/guide/masking.md ("Maskers") has when it helps and when it costs.
    ground_removal: bool = False
    ground_tolerance: float = 1.0  # px above the road line still counted as road
    # Plausible camera heights over the road (m): road slopes a = baseline / height
    # outside baseline/max .. baseline/min are rejected (a truck filling the view).
    ground_min_height: float = 0.8
    ground_max_height: float = 3.0  # m, see ground_min_height
    ground_baseline: float = 0.0  # m; 0 = the rig's (its calibration), else 0.54 (KITTI)
    ground_fit_tolerance: float = 1.0  # px: Hough bin width / inlier distance of the fit
    ground_min_inliers: int = 150  # fewer sampled road points -> unreliable, no removal
    ground_rows_from: float = 0.4  # fit on the rows below this fraction of the image height
    # The road may take at most this fraction of an object's in-peak pixels; more means
    # the line does not hold at the object (slope, kerb): no removal there. 1 = no check.
    ground_max_fraction: float = 0.5
    ground_after_dilate: bool = True  # the dilation must not grow into the road either

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Range checks (ConfigError naming the key); run whenever one is made or loaded."""
        def key(k: str) -> str:
            return f"masker.outline.{k}"

        if self.transfer not in TRANSFER_MODES:
            raise _bad(key("transfer"), "one of " + ", ".join(TRANSFER_MODES), self.transfer)
        if not (0 < self.ground_min_height < self.ground_max_height):
            raise ConfigError(
                "masker.outline.ground_min_height must be > 0 and below ground_max_height, got "
                f"{self.ground_min_height} and {self.ground_max_height}"
            )
        if self.ground_tolerance < 0 or self.ground_fit_tolerance <= 0:
            raise ConfigError(
                "masker.outline.ground_tolerance must be >= 0 and ground_fit_tolerance > 0, got "
                f"{self.ground_tolerance} and {self.ground_fit_tolerance}"
            )
        if not (0.0 <= self.ground_rows_from < 1.0):
            raise _bad(key("ground_rows_from"), "in [0, 1)", self.ground_rows_from)
        if not (0.0 <= self.carry_max_scale < 1.0) or self.carry_max_shift < 0:
            raise _bad(key("carry_max_scale / carry_max_shift"), "in [0, 1) / >= 0",
                       (self.carry_max_scale, self.carry_max_shift))
        for k in ("overlap_weight", "claim_fraction", "ground_max_fraction", "min_outline_fraction",
                  "min_valid_fraction", "near_peak_ratio", "peak_extend_ratio"):
            v = getattr(self, k)
            if not (0.0 <= v <= 1.0):
                raise _bad(key(k), "in [0, 1]", v)
        for k in ("bin_width", "peak_tolerance"):
            if not getattr(self, k) > 0:
                raise _bad(key(k), "> 0", getattr(self, k))
        for k in ("peak_tolerance_rel", "ground_baseline"):
            if getattr(self, k) < 0:
                raise _bad(key(k), ">= 0", getattr(self, k))
        for k in ("min_box_pixels", "min_box_side", "dilate", "ground_min_inliers"):
            if getattr(self, k) < 0:
                raise _bad(key(k), ">= 0", getattr(self, k))


@dataclass
class MaskerConfig:
    kind: MaskerKind = "outline"  # outline (default), box, seg (a segmentation baseline) or none
    outline: OutlineConfig = field(default_factory=OutlineConfig)
    seg_model: str = "yolov8n-seg-int8"  # the segmentation model of masker seg
    box_margin: int = 0  # px added around each box (masker box)

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        if str(self.kind).lower() not in MASKER_KINDS:
            raise _bad("masker.kind", "one of " + ", ".join(MASKER_KINDS), self.kind)
        if self.box_margin < 0:
            raise _bad("masker.box_margin", ">= 0", self.box_margin)
        self.outline.validate()


MotionMode = Literal["moving", "all"]
MOTION_MODES: tuple[str, ...] = typing.get_args(MotionMode)


@dataclass
class MotionConfig:
    """Which detected objects are masked (``objects/motion``, docs/guide/masking.md "Mask only what
    moves"): ``mode: moving`` (default) masks an object only while the stereo motion test
    judges it moving or has not judged it yet -- static (parked) objects take part in
    tracking and mapping; ``mode: all`` masks every detection (the thesis' behavior, for
    comparison).

    The test: up to ``max_points`` corners on each tracked object's outline are followed
    from frame to frame by optical flow, with the masker's disparity at every frame.
    (1) Frame to frame: a static object's point at k-1, moved by SLAM's camera motion and
    projected, must land on its measurement at k; the residual in (u, v, disparity) is
    weighed by its covariance (``sigma_px``, ``sigma_disparity`` at both frames,
    propagated through the prediction: the stereo depth uncertainty) against the
    chi-square bound ``chi2`` (3 dof).  (2) Over up to ``window_frames`` frames: the
    object's world velocity, the median of its points' displacements since they were
    first seen, against its covariance (stereo, points counted at most
    ``object_points`` times, SLAM's pose error ``sigma_pose_deg`` / ``sigma_pose_m`` per
    frame): chi-square ``object_chi2``.  A frame is evidence of motion when at least
    ``moving_fraction`` of the points exceed (1) or the velocity exceeds (2); of rest
    when at most ``static_fraction`` of the points exceed (1), the velocity's chi-square
    is at most ``object_chi2_static``, there are ``min_points`` points, and -- for the
    slow road users, persons and bicycles -- it is near enough for the window test to tell
    rest from ``rest_resolution`` m/s at all (twice the stereo noise of a velocity over
    the whole window at its distance; a farther walker or cyclist stays undecided, masked;
    opt-in, off by default: ``rest_resolution_vehicle`` the same for vehicles, and
    ``rest_sigma: measured`` the object's own velocity noise instead of a whole window's).
    The window velocity is a median over the points, and its noise that of a median of
    points of unequal noise (``velocity_noise: median``; ``mean``: the mean point
    covariance's, which the points first seen a frame ago dominate).
    ``confirm_frames`` frames of evidence in a row decide an undecided object or turn a
    static one moving (its map points are then removed, ``forget_points``); one frame that
    fails both tests on ``min_points`` points or more decides an undecided object moving
    (``strong_confirm``); a moving one is judged static again after as many frames of rest
    in a row as it gave of motion, at least ``confirm_frames`` and at most
    ``release_frames``, when it is near enough for the window test to tell its rest from
    ``rest_resolution`` (``release: proportional``; farther, or ``fixed``: ``release_frames``).  A frame in
    which at least ``suspect_fraction`` of the objects judged static seem to move gives no
    evidence (SLAM's pose is suspect), and the window's displacements start again after it
    (``suspect_restarts_window``).  An undecided object whose box overlaps a judged
    object of its class group by IoU >= ``duplicate_iou`` is a second detection of it (a
    detector names one car ``car`` and ``truck``): it takes that object's verdict."""

    mode: MotionMode = "moving"  # moving: mask objects judged moving or not yet judged; all: every detection
    sigma_px: float = 0.5
    sigma_disparity: float = 0.5
    sigma_pose_deg: float = 0.05
    sigma_pose_m: float = 0.02
    chi2: float = 11.34  # 99 % of chi-square with 3 degrees of freedom
    moving_fraction: float = 0.5
    static_fraction: float = 0.25
    min_points: int = 5
    max_points: int = 20  # corners followed per object
    object_chi2: float = 11.34
    object_chi2_static: float = 6.25
    rest_resolution: float = 2.0  # m/s
    # the same rule for vehicles (m/s; None: vehicles are judged at any range)
    rest_resolution_vehicle: float | None = None
    # the velocity noise the rule weighs: "window" = a full window's at the object's distance,
    # "measured" = the object's own velocity covariance this frame (its points' actual ages)
    rest_sigma: str = "window"
    object_points: int = 10
    window_frames: int = 15
    confirm_frames: int = 2
    release_frames: int = 8
    suspect_fraction: float = 0.67
    forget_points: bool = True
    duplicate_iou: float = 0.7
    # the window velocity's noise: "median" = of a median of points of unequal ages (the few
    # points first seen a frame ago barely move it), "mean" = of their mean (the mean point covariance)
    velocity_noise: str = "median"
    # after a suspect frame (a pose that may have jumped) the window's displacements start there
    suspect_restarts_window: bool = True
    # a mover is judged static again after min(release_frames, max(confirm_frames, its frames of
    # motion evidence)) frames of rest ("proportional"; only when near enough to tell rest from
    # rest_resolution, as the far-walker rule, else release_frames), or after release_frames ("fixed")
    release: str = "proportional"
    # an undecided object judged moving on one frame that fails both tests (at least
    # moving_fraction of min_points points or more over chi2, and the window's chi-square over
    # object_chi2); undecided and moving objects are both masked, so only the verdict comes sooner
    strong_confirm: bool = True

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        if str(self.mode).lower() not in MOTION_MODES:
            raise _bad("motion.mode", "one of " + ", ".join(MOTION_MODES), self.mode)
        if self.object_chi2_static > self.object_chi2:
            raise ConfigError("motion.object_chi2_static must be at most motion.object_chi2, got "
                              f"{self.object_chi2_static!r} > {self.object_chi2!r}")
        if self.object_points < 1:
            raise _bad("motion.object_points", ">= 1", self.object_points)
        for k in ("sigma_px", "sigma_disparity", "chi2", "object_chi2", "object_chi2_static", "rest_resolution"):
            if not getattr(self, k) > 0:
                raise _bad(f"motion.{k}", "> 0", getattr(self, k))
        if self.rest_sigma not in ("window", "measured"):
            raise _bad("motion.rest_sigma", "window or measured", self.rest_sigma)
        if self.release not in ("proportional", "fixed"):
            raise _bad("motion.release", "proportional or fixed", self.release)
        if self.velocity_noise not in ("median", "mean"):
            raise _bad("motion.velocity_noise", "median or mean", self.velocity_noise)
        if self.rest_resolution_vehicle is not None and not self.rest_resolution_vehicle > 0:
            raise _bad("motion.rest_resolution_vehicle", "> 0 (or null: vehicles judged at any range)",
                       self.rest_resolution_vehicle)
        for k in ("moving_fraction", "static_fraction"):
            if not 0.0 <= getattr(self, k) <= 1.0:
                raise _bad(f"motion.{k}", "in [0, 1]", getattr(self, k))
        if self.static_fraction >= self.moving_fraction:
            raise ConfigError("motion.static_fraction must be below motion.moving_fraction, got "
                              f"{self.static_fraction!r} >= {self.moving_fraction!r}")
        if self.min_points < 3:
            raise _bad("motion.min_points", ">= 3", self.min_points)
        if self.max_points < self.min_points:
            raise _bad("motion.max_points", f">= motion.min_points ({self.min_points})", self.max_points)
        for k in ("sigma_pose_deg", "sigma_pose_m"):
            if not getattr(self, k) >= 0:
                raise _bad(f"motion.{k}", ">= 0", getattr(self, k))
        for k in ("suspect_fraction", "duplicate_iou"):
            if not 0.0 < getattr(self, k) <= 1.0:
                raise _bad(f"motion.{k}", "in (0, 1]", getattr(self, k))
        for k in ("confirm_frames", "release_frames", "window_frames"):
            if getattr(self, k) < 1:
                raise _bad(f"motion.{k}", ">= 1", getattr(self, k))


# "process": the former worker process, now the same as "thread" (old configuration files)
LocalBAMode = Literal["thread", "inline", "off", "process"]
LOCAL_BA_MODES: tuple[str, ...] = typing.get_args(LocalBAMode)
LocalMappingMode = Literal["thread", "inline"]
LOCAL_MAPPING_MODES: tuple[str, ...] = typing.get_args(LocalMappingMode)


@dataclass
class SlamConfig:
    """Stereo SLAM back-end (ORB-SLAM2-style tracking + local mapping), ``dynastereo.slam``.

    Names follow ORB-SLAM2's settings where one exists (``ORBextractor.nFeatures`` ->
    ``n_features``, ``ThDepth`` -> ``th_depth``); ORB-SLAM2 settings files are read with
    :func:`orbslam2_slam_values`.
    """

    # ORB extractor
    n_features: int = 2000  # ORBextractor.nFeatures
    scale_factor: float = 1.2  # ORBextractor.scaleFactor
    n_levels: int = 8  # ORBextractor.nLevels
    ini_th_fast: int = 20  # ORBextractor.iniThFAST: FAST threshold
    min_th_fast: int = 7  # ORBextractor.minThFAST: levels short of corners at ini_th_fast retry with it
    oversample: float = 2.0  # corners detected per kept one, before grid bucketing
    mask_margin: int = 0  # grow the dynamic mask by this many pixels before detection
    # stereo
    th_depth: float = 35.0  # ThDepth: close/far threshold, in baselines
    # px added to every measured disparity (a right principal-point error of the
    # rectification); the start value when self_calibrate
    disparity_offset: float = 0.0
    # estimate the disparity offset when the map has selfcal_keyframes keyframes: BA over
    # the whole map solved at a few offsets (needs local_ba thread / inline), slam/selfcal.py
    self_calibrate: bool = True
    selfcal_keyframes: int = 8  # see self_calibrate
    # the estimate is refined over the whole map at 1.5x, 2.25x... selfcal_keyframes
    # keyframes: this many estimates in all
    selfcal_rounds: int = 4
    # no offset is applied until an estimate is this many sigmas from 0 (the later rounds
    # then refine it)
    selfcal_min_sigmas: float = 2.0
    # tracking
    min_inliers: int = 20  # fewer inliers after local-map tracking -> pose not supported
    # fewer inliers than this fraction of the median of the last 5 tracked frames -> pose
    # not supported either (a wrong pose keeps a few far points: a jump back in a revisit)
    min_inlier_fraction: float = 0.25
    # an unsupported pose is replaced by a prior-free search over the map's keyframes
    # (bag-of-words database -> best reloc_candidates keyframes -> PnP-RANSAC -> local map);
    # its best hypothesis needs reloc_min_inliers, else the frame is lost.  0 = no search
    reloc_candidates: int = 3
    reloc_min_inliers: int = 50  # see reloc_candidates
    min_init_points: int = 100  # stereo points needed to (re)initialize a map
    max_frames: int = 10  # keyframe at least every max_frames (ORB-SLAM2: camera fps)
    min_frames: int = 0  # no keyframe before min_frames frames since the last one
    # local mapping
    local_ba: LocalBAMode = "thread"  # in a thread beside tracking, inline, or none
    # a new keyframe's local mapping and loop closing: in their own thread beside the next
    # frame's features and stereo matching (joined before that frame is tracked: the same
    # result as inline), or inline
    local_mapping: LocalMappingMode = "thread"
    ba_iterations: int = 5  # robust (Huber) LM iterations per local BA (ORB-SLAM2: 5)
    ba_refine_iterations: int = 10  # then outliers dropped, iterations without the kernel (ORB-SLAM2: 10)
    # bound on the wait for a local BA's result when it is due; past it the BA is aborted
    # and its result skipped (run.json stats.local_ba_fallbacks).  A local BA takes
    # ~10-50 ms, the self-calibrating one ~0.1-1 s
    ba_wait_s: float = 5.0
    ba_max_keyframes: int = 10  # optimized keyframes (current + best covisible)
    ba_max_fixed: int = 10  # fixed keyframes that anchor the local window
    ba_lag_frames: int = 2  # a local BA submitted at frame k is applied after tracking frame k+lag
    triangulation_neighbours: int = 6  # covisible keyframes searched for new points
    fuse_neighbours: int = 6  # covisible keyframes searched for duplicate points
    keyframe_culling: bool = True  # remove keyframes whose points others see (ORB-SLAM2's culling)
    # loop closing and place recognition (bag of words)
    loop_closing: bool = True  # detect and close loops (off: --no-loop-closing)
    vocabulary: str = ""  # ORB vocabulary file (dynastereo vocab); "" = the built-in one
    loop_min_kf_gap: int = 10  # keyframes since the map's start / the last loop before detecting
    loop_consistency: int = 3  # consecutive keyframes agreeing on a loop candidate
    loop_min_matches: int = 20  # descriptor matches to a candidate before RANSAC
    loop_min_inliers: int = 40  # inliers of the loop's geometric verification
    # of those, at least this many close stereo points (closer than th_depth baselines in
    # the new keyframe): far points leave the distance along the view direction weak
    loop_min_close_inliers: int = 20
    loop_max_verify: int = 2  # consistent candidates verified per keyframe, best first
    loop_covis_edge_weight: int = 100  # essential-graph covisibility edges (ORB-SLAM2: 100)
    loop_full_ba: bool = True  # full bundle adjustment (BA thread) after each loop
    loop_full_ba_iterations: int = 20  # iterations of the full BA after a loop
    loop_ba_lag_frames: int = 20  # the full BA is applied this many frames after the loop
    loop_ba_wait_s: float = 60.0  # bound on the wait for the full BA when due (then skipped)
    threads: int = 2  # threads for feature extraction (left/right in parallel)

    def __post_init__(self) -> None:
        self.validate()

    @property
    def mapping_on(self) -> bool:
        """Local BA runs (and with it self-calibration and the loops' full BA)."""
        return self.local_ba != "off"

    def validate(self) -> None:
        """Range checks (ConfigError naming the key); run whenever one is made or loaded."""
        import math

        def key(k: str) -> str:
            return f"slam.{k}"

        if self.n_features < 50:
            raise _bad(key("n_features"), ">= 50", self.n_features)
        if not self.scale_factor > 1.0:
            raise _bad(key("scale_factor"), "> 1", self.scale_factor)
        if not 1 <= self.n_levels <= 32:
            raise _bad(key("n_levels"), "in 1..32", self.n_levels)
        if not (0 < self.min_th_fast <= self.ini_th_fast <= 255):
            raise ConfigError(f"slam.min_th_fast and slam.ini_th_fast must satisfy 0 < min <= ini <= 255, got "
                              f"{self.min_th_fast} and {self.ini_th_fast}")
        if not self.oversample >= 1.0:
            raise _bad(key("oversample"), ">= 1", self.oversample)
        if self.local_ba == "process":  # the old name of "thread"
            self.local_ba = "thread"
        if self.local_ba not in LOCAL_BA_MODES:
            raise _bad(key("local_ba"), "one of " + ", ".join(LOCAL_BA_MODES), self.local_ba)
        if self.local_mapping not in LOCAL_MAPPING_MODES:
            raise _bad(key("local_mapping"), "one of " + ", ".join(LOCAL_MAPPING_MODES), self.local_mapping)
        if self.th_depth <= 0:
            raise _bad(key("th_depth"), "positive", self.th_depth)
        if not 0.0 <= self.min_inlier_fraction < 1.0:
            raise _bad(key("min_inlier_fraction"), "in [0, 1)", self.min_inlier_fraction)
        if self.reloc_candidates < 0 or self.reloc_min_inliers < 0:
            raise ConfigError("slam.reloc_candidates and slam.reloc_min_inliers must be >= 0")
        if self.loop_consistency < 0 or self.loop_min_inliers < 10 or self.loop_ba_lag_frames < 0:
            raise ConfigError(
                "slam.loop_consistency must be >= 0, slam.loop_min_inliers >= 10 and slam.loop_ba_lag_frames >= 0"
            )
        if self.selfcal_rounds < 1:
            raise _bad(key("selfcal_rounds"), ">= 1", self.selfcal_rounds)
        if self.selfcal_keyframes < 3:
            raise _bad(key("selfcal_keyframes"), ">= 3", self.selfcal_keyframes)
        if not math.isfinite(self.disparity_offset) or abs(self.disparity_offset) > 5.0:
            raise _bad(key("disparity_offset"), "a few pixels at most", self.disparity_offset)
        for k in ("mask_margin", "min_inliers", "min_init_points", "min_frames", "ba_lag_frames",
                  "triangulation_neighbours", "fuse_neighbours", "loop_min_kf_gap", "loop_min_matches",
                  "loop_min_close_inliers", "loop_covis_edge_weight", "selfcal_min_sigmas"):
            if getattr(self, k) < 0:
                raise _bad(key(k), ">= 0", getattr(self, k))
        for k in ("max_frames", "ba_iterations", "ba_max_keyframes", "loop_max_verify", "loop_full_ba_iterations",
                  "threads"):
            if getattr(self, k) < 1:
                raise _bad(key(k), ">= 1", getattr(self, k))
        if self.ba_max_fixed < 0:
            raise _bad(key("ba_max_fixed"), ">= 0", self.ba_max_fixed)
        if self.ba_refine_iterations < 0:
            raise _bad(key("ba_refine_iterations"), ">= 0", self.ba_refine_iterations)
        for k in ("ba_wait_s", "loop_ba_wait_s"):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise _bad(key(k), "a positive number of seconds", v)


# ORB-SLAM2 settings-file keys that set SlamConfig fields (Camera.fps -> max_frames too)
ORBSLAM2_SLAM_KEYS: dict[str, str] = {
    "ORBextractor.nFeatures": "n_features",
    "ORBextractor.scaleFactor": "scale_factor",
    "ORBextractor.nLevels": "n_levels",
    "ORBextractor.iniThFAST": "ini_th_fast",
    "ORBextractor.minThFAST": "min_th_fast",
    "ThDepth": "th_depth",
}


def orbslam2_slam_values(settings: dict[str, Any], path: str | Path | None = None) -> dict[str, Any]:
    """The ``slam`` section values an ORB-SLAM2 settings file sets (``ORBSLAM2_SLAM_KEYS``,
    and ``Camera.fps`` as ``max_frames`` when positive) -- the one adapter, used by
    :func:`load_config` and :func:`dynastereo.slam.settings.slam_config_from_orbslam`."""
    hints = typing.get_type_hints(SlamConfig)
    out: dict[str, Any] = {}
    items = [(k, f) for k, f in ORBSLAM2_SLAM_KEYS.items() if k in settings]
    if "Camera.fps" in settings:
        items.append(("Camera.fps", "max_frames"))
    for k, name in items:
        try:
            value = float(settings[k])
        except (TypeError, ValueError):
            raise ConfigError(f"'{k}' must be a number, got {settings[k]!r}", path) from None
        if k == "Camera.fps":
            if value <= 0:
                continue
            value = round(value)
        if hints[name] is int and value != int(value):
            raise ConfigError(f"'{k}' must be an integer, got {settings[k]!r}", path)
        out[name] = int(value) if hints[name] is int else value
    return out


@dataclass
class ObjectsConfig:
    """The objects' world positions (``objects/world.py``, docs/guide/objects.md).

    ``block_size`` (odd, 5-255; default 11): every outline's pixels are matched again with
    that block, compiled, in a window around the masker's disparities there, with StereoBM's
    checks as ``stereo.*`` sets them (``objects/disparity.py``) -- positions from a
    smaller block than the masks want, without the masks and the motion test paying for it
    (synthetic held-out positions 0.288 m against 0.310 m with the masker's 15-px disparity;
    docs/design/objects-motion.md).  ``0``: from the masker's disparity inside each outline (its
    ``stereo.block_size``, 15), a few tenths of a millisecond a frame cheaper.  ``stride``:
    every stride-th row and column matched at least (2: a quarter of the work)."""

    block_size: int = 11
    stride: int = 1

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        if self.block_size != 0 and (self.block_size % 2 != 1 or not (5 <= self.block_size <= 255)):
            raise _bad("objects.block_size", "0 (the masker's disparity) or odd and in [5, 255]", self.block_size)
        if not (1 <= self.stride <= 8):
            raise _bad("objects.stride", "in [1, 8]", self.stride)



# Every numeric key's bounds (inclusive), checked with finiteness whenever a Config is made
# or loaded: a value past them (``masker.outline.dilate: 100000`` would allocate tens of
# GB; ``motion.chi2: .inf`` turns the motion test off unseen) is a one-line ConfigError
# naming the key.  tests/test_config.py checks that every numeric key has its bounds here.
BOUNDS: dict[str, tuple[float, float]] = {
    "stereo.min_disparity": (-256, 256), "stereo.num_disparities": (16, 1024), "stereo.block_size": (1, 255),
    "stereo.p1": (0, 10_000_000), "stereo.p2": (0, 10_000_000), "stereo.disp12_max_diff": (-1, 1024),
    "stereo.pre_filter_cap": (1, 255), "stereo.uniqueness_ratio": (0, 100), "stereo.speckle_window_size": (0, 10_000),
    "stereo.speckle_range": (0, 1024), "stereo.texture_threshold": (0, 100_000), "stereo.wls_lambda": (0, 1e6),
    "stereo.wls_sigma": (0, 100), "stereo.scale": (1, 4),
    "detector.score_threshold": (0, 1), "detector.nms_threshold": (0, 1), "detector.input_size": (32, 4096),
    "detector.threads": (0, 256), "detector.min_box_size": (0, 10_000), "detector.scale": (0.05, 8),
    "detector.tiles": (1, 16), "detector.tile_overlap": (0, 1), "detector.band_top": (0, 1),
    "detector.interval": (1, 1000), "detector.max_carry": (0, 1000), "detector.carry_downscale": (1, 16),
    "masker.outline.bin_width": (0, 64), "masker.outline.peak_tolerance": (0, 256),
    "masker.outline.peak_tolerance_rel": (0, 1), "masker.outline.min_valid_fraction": (0, 1),
    "masker.outline.min_box_pixels": (0, 10_000_000), "masker.outline.min_box_side": (0, 10_000),
    "masker.outline.dilate": (0, 64), "masker.outline.near_peak_ratio": (0, 1),
    "masker.outline.peak_extend_ratio": (0, 1), "masker.outline.min_outline_fraction": (0, 1),
    "masker.outline.carry_max_scale": (0, 1), "masker.outline.carry_max_shift": (0, 10),
    "masker.outline.overlap_weight": (0, 1), "masker.outline.claim_fraction": (0, 1),
    "masker.outline.ground_tolerance": (0, 64), "masker.outline.ground_min_height": (0, 100),
    "masker.outline.ground_max_height": (0, 100), "masker.outline.ground_baseline": (0, 10),
    "masker.outline.ground_fit_tolerance": (0, 64), "masker.outline.ground_min_inliers": (0, 10_000_000),
    "masker.outline.ground_rows_from": (0, 1), "masker.outline.ground_max_fraction": (0, 1),
    "masker.box_margin": (0, 512),
    "slam.n_features": (50, 100_000), "slam.scale_factor": (1, 4), "slam.n_levels": (1, 32),
    "slam.ini_th_fast": (1, 255), "slam.min_th_fast": (1, 255), "slam.oversample": (1, 64), "slam.mask_margin": (0, 512),
    "slam.th_depth": (0, 10_000), "slam.disparity_offset": (-5, 5), "slam.selfcal_keyframes": (3, 10_000),
    "slam.selfcal_rounds": (1, 100), "slam.selfcal_min_sigmas": (0, 100), "slam.min_inliers": (0, 100_000),
    "slam.min_inlier_fraction": (0, 1), "slam.reloc_candidates": (0, 1000), "slam.reloc_min_inliers": (0, 100_000),
    "slam.min_init_points": (0, 100_000), "slam.max_frames": (1, 100_000), "slam.min_frames": (0, 100_000),
    "slam.ba_iterations": (1, 1000), "slam.ba_refine_iterations": (0, 1000), "slam.ba_wait_s": (0, 86_400),
    "slam.ba_max_keyframes": (1, 1000), "slam.ba_max_fixed": (0, 1000), "slam.ba_lag_frames": (0, 1000),
    "slam.triangulation_neighbours": (0, 1000), "slam.fuse_neighbours": (0, 1000),
    "slam.loop_min_kf_gap": (0, 1_000_000), "slam.loop_consistency": (0, 1000), "slam.loop_min_matches": (0, 100_000),
    "slam.loop_min_inliers": (10, 100_000), "slam.loop_min_close_inliers": (0, 100_000),
    "slam.loop_max_verify": (1, 1000), "slam.loop_covis_edge_weight": (0, 100_000),
    "slam.loop_full_ba_iterations": (1, 1000), "slam.loop_ba_lag_frames": (0, 100_000),
    "slam.loop_ba_wait_s": (0, 86_400), "slam.threads": (1, 256),
    "motion.sigma_px": (0, 100), "motion.sigma_disparity": (0, 100), "motion.sigma_pose_deg": (0, 90),
    "motion.sigma_pose_m": (0, 100), "motion.chi2": (0, 1e6), "motion.moving_fraction": (0, 1),
    "motion.static_fraction": (0, 1), "motion.min_points": (3, 10_000), "motion.max_points": (3, 10_000),
    "motion.object_chi2": (0, 1e6), "motion.object_chi2_static": (0, 1e6), "motion.rest_resolution": (0, 1000),
    "motion.rest_resolution_vehicle": (0, 1000), "motion.object_points": (1, 10_000), "motion.window_frames": (1, 10_000),
    "motion.confirm_frames": (1, 10_000), "motion.release_frames": (1, 10_000), "motion.suspect_fraction": (0, 1),
    "motion.duplicate_iou": (0, 1),
    "objects.block_size": (0, 255), "objects.stride": (1, 8),
    "mesh.block_size": (1, 255), "mesh.scale": (1, 4), "mesh.voxel_size": (0, 10), "mesh.truncation": (0, 100),
    "mesh.min_depth": (0, 1000), "mesh.max_depth": (0.1, 1000), "mesh.confidence": (0, 100), "mesh.max_step": (0, 1000),
    "mesh.mask_margin": (0, 64), "mesh.bleed_margin": (0, 128), "mesh.min_weight": (1, 1000),
    "seed": (0, 2**32 - 1),
}


def numeric_keys(obj: Any, prefix: str = "") -> typing.Iterator[tuple[str, Any]]:
    """``(dotted key, value)`` of every int / float key of a configuration (bools and
    strings left out; an optional number's None too)."""
    hints = typing.get_type_hints(type(obj))
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            yield from numeric_keys(v, f"{prefix}{f.name}.")
            continue
        args = set(typing.get_args(hints[f.name])) - {type(None)} or {hints[f.name]}
        if args & {int, float} and not args & {bool, str}:
            yield f"{prefix}{f.name}", v


def check_bounds(cfg: Any) -> None:
    """Every numeric key finite and within :data:`BOUNDS` (ConfigError naming the key)."""
    import math

    for key, v in numeric_keys(cfg):
        if v is None or isinstance(v, bool):
            continue
        lo, hi = BOUNDS[key]
        if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
            raise _bad(key, f"a finite number in [{lo:g}, {hi:g}]", v)


#: the finest TSDF voxel and the widest truncation, in voxels (mesh.voxel_size, mesh.truncation)
MIN_VOXEL_M = 0.01
MAX_TRUNCATION_VOXELS = 32


@dataclass
class MeshConfig:
    """The dense, mover-free mesh of the static world (``run --save-mesh``, ``mesh/``).

    Each keyframe's full-frame disparity (OpenCV's ``algorithm`` with ``block_size`` at
    1/``scale`` resolution, the other matcher settings from ``stereo``; ``confidence`` its
    uniqueness margin), outside the masks of objects judged moving or not yet judged (grown
    by ``mask_margin`` px; within ``bleed_margin`` px of them, pixels at the depth of the mover
    beside them, +- 1 m, left out too: its disparity smeared over the background), between ``min_depth`` and ``max_depth`` m, is fused at the final
    poses into a TSDF of ``voxel_size`` m voxels truncated at ``truncation`` m; marching
    cubes gives the mesh, kept where a voxel was seen ``min_weight`` times.  Defaults suit
    KITTI (fx 720 px, baseline 0.54 m): semi-global matching at half resolution, 13 ms of
    CPU a keyframe, where the masks' block matcher leaves smooth asphalt empty."""

    algorithm: StereoAlgorithm = "sgbm3way"
    block_size: int = 5  # odd
    scale: int = 2  # the disparity's downscale factor (1, 2 or 4)
    voxel_size: float = 0.1  # m
    truncation: float = 0.3  # m, >= voxel_size
    min_depth: float = 1.0  # m
    max_depth: float = 20.0  # m
    confidence: int = 15  # disparity confidence: the best match beats every other by this %, 0: all
    max_step: float = 2.0  # px: a second difference of the disparity above it marks an edge (flying pixels), left out
    mask_margin: int = 8  # px the movers' masks are grown by (half the matcher's block: its border bleed)
    bleed_margin: int = 24  # px around the movers where a pixel at the depth of the mover beside it (+-1 m) is left out too
    min_weight: int = 1  # observations a voxel needs to carry the surface
    compare: bool = False  # also fuse the keyframes with the masks ignored: FILE_unmasked.ply, the report shows both

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        if str(self.algorithm).lower() not in STEREO_ALGORITHMS:
            raise _bad("mesh.algorithm", "one of " + ", ".join(STEREO_ALGORITHMS), self.algorithm)
        lo = 5 if str(self.algorithm).lower() == "bm" else 1
        if self.block_size % 2 != 1 or not (lo <= self.block_size <= 255):
            raise _bad("mesh.block_size", f"odd and in [{lo}, 255] for {self.algorithm}", self.block_size)
        if self.scale not in STEREO_SCALES:
            raise _bad("mesh.scale", f"one of {STEREO_SCALES}", self.scale)
        # the voxel grid's memory grows as 1 / voxel_size^2 (blocks along the surfaces) and
        # with truncation / voxel_size (blocks behind and before them): both bounded
        if not self.voxel_size >= MIN_VOXEL_M:
            raise _bad("mesh.voxel_size", f"> 0 m and at least {MIN_VOXEL_M:g} m (the grid's memory grows as "
                       "1/voxel^2)", self.voxel_size)
        if not self.voxel_size <= self.truncation <= MAX_TRUNCATION_VOXELS * self.voxel_size:
            raise ConfigError(f"mesh.truncation must be at least one voxel and at most {MAX_TRUNCATION_VOXELS} "
                              f"(mesh.voxel_size {self.voxel_size:g} m), got {self.truncation!r}")
        if not 0 < self.min_depth < self.max_depth:
            raise ConfigError(f"mesh.min_depth and mesh.max_depth must satisfy 0 < min_depth < max_depth, got "
                              f"{self.min_depth!r} and {self.max_depth!r}")
        if not 0 <= self.confidence <= 100:
            raise _bad("mesh.confidence", "in [0, 100] (%)", self.confidence)
        if not self.max_step > 0:
            raise _bad("mesh.max_step", "> 0 px", self.max_step)
        if not 0 <= self.mask_margin <= 64:
            raise _bad("mesh.mask_margin", "in [0, 64] px", self.mask_margin)
        if not 0 <= self.bleed_margin <= 128:
            raise _bad("mesh.bleed_margin", "in [0, 128] px", self.bleed_margin)
        if not 1 <= self.min_weight <= 1000:
            raise _bad("mesh.min_weight", "in [1, 1000]", self.min_weight)


@dataclass
class Config:
    stereo: StereoConfig = field(default_factory=StereoConfig)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    masker: MaskerConfig = field(default_factory=MaskerConfig)
    slam: SlamConfig = field(default_factory=SlamConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    objects: ObjectsConfig = field(default_factory=ObjectsConfig)
    mesh: MeshConfig = field(default_factory=MeshConfig)
    seed: int = 0  # seed of the SLAM's random choices (RANSAC): the same seed, the same run

    def __post_init__(self) -> None:
        if self.seed < 0:
            raise _bad("seed", ">= 0", self.seed)
        check_bounds(self)

    def validate(self) -> None:
        """Every section's checks again (a configuration changed after it was made)."""
        for section in (self.stereo, self.detector, self.masker, self.slam, self.motion, self.objects, self.mesh):
            section.validate()
        self.__post_init__()

    def with_overrides(self, overrides: dict[str, Any]) -> "Config":
        """Return a copy with dotted-key overrides applied (``{"stereo.wls": True}``)."""
        data = to_dict(self)
        try:
            nest_dotted({k: v for k, v in overrides.items() if v is not None}, data, known_only=True)
        except KeyError as e:
            raise ConfigError(f"unknown configuration key '{e.args[0]}'") from None
        return from_dict(Config, data, "<overrides>")


def to_dict(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    return obj


# Values from YAML or a command line's text.  cattrs walks the dataclass tree (sections,
# ``X | None``, unknown keys, which key an error is at); the hooks below are the rules for
# one value: what a command line's text may mean ("true", "9", "SGBM", "car,person").


class _BadValue(ValueError):
    """A value a hook refuses, ``must be <what>, got <value>``; from_dict adds the key."""


def _to_bool(value: Any, _tp: Any = bool) -> bool:
    if isinstance(value, bool):
        return value
    if isinstance(value, str) and value.strip().lower() in ("true", "false"):  # a command line's text
        return value.strip().lower() == "true"
    if isinstance(value, int) and value in (0, 1):
        return bool(value)
    raise _BadValue(f"must be true/false, got {value!r}")


def _to_int(value: Any, _tp: Any = int) -> int:
    try:
        f = None if isinstance(value, bool) else float(value)
    except (TypeError, ValueError):
        f = None
    if f is None or not f.is_integer():
        raise _BadValue(f"must be an integer, got {value!r}")
    return int(f)


def _to_float(value: Any, _tp: Any = float) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        raise _BadValue(f"must be a number, got {value!r}") from None


def _to_str(value: Any, _tp: Any = str) -> str:
    if not isinstance(value, (str, int, float)):
        raise _BadValue(f"must be a string, got {value!r}")
    return str(value)


def _to_choice(value: Any, tp: Any) -> Any:
    args = typing.get_args(tp)
    if isinstance(value, str) and value.lower() in args:
        return value.lower()
    if value in args and not isinstance(value, bool):
        return value
    raise _BadValue(f"must be one of {', '.join(map(str, args))}, got {value!r}")


def _to_list(value: Any, tp: Any) -> list:
    if isinstance(value, str):
        value = [v.strip() for v in value.split(",") if v.strip()]
    if not isinstance(value, (list, tuple)):
        raise _BadValue(f"must be a list, got {value!r}")
    args = typing.get_args(tp)
    return [_converter.structure(v, args[0] if args else Any) for v in value]


def _section_hook(cls: type) -> Any:
    structure = cattrs.gen.make_dict_structure_fn(cls, _converter)

    def to_section(value: Any, _tp: Any) -> Any:
        if not isinstance(value, dict):
            raise _BadValue(f"must be a mapping, got {type(value).__name__}")
        return structure(value, cls)

    return to_section


_converter = cattrs.Converter(forbid_extra_keys=True, detailed_validation=True)
for _tp, _hook in ((bool, _to_bool), (int, _to_int), (float, _to_float), (str, _to_str)):
    _converter.register_structure_hook(_tp, _hook)
_converter.register_structure_hook_func(lambda tp: typing.get_origin(tp) is Literal, _to_choice)
_converter.register_structure_hook_func(lambda tp: typing.get_origin(tp) is list, _to_list)
_converter.register_structure_hook_factory(dataclasses.is_dataclass, _section_hook)


def _errors(exc: BaseException, path: tuple[str, ...] = ()) -> typing.Iterator[tuple[tuple[str, ...], BaseException]]:
    """``(key path, error)`` of every error in cattrs' exception tree."""
    if isinstance(exc, cattrs.ClassValidationError):
        with_notes, without = exc.group_exceptions()
        for e, note in with_notes:
            yield from _errors(e, path + (note.name,))
        for e in without:
            yield from _errors(e, path)
    else:
        yield path, exc


def from_dict(cls: type, data: dict[str, Any], where: str = "") -> Any:
    """``cls`` (a configuration dataclass) from a nested mapping; the first bad key or
    value raises a one-line ConfigError naming the key (``where``: a prefix of the keys;
    ``"<...>"`` names no prefix)."""
    prefix = () if not where or where.startswith("<") else tuple(where.split("."))
    try:
        return _converter.structure(data, cls)
    except (cattrs.ClassValidationError, _BadValue) as exc:
        found = list(_errors(exc, prefix))

    def order(pe: tuple[tuple[str, ...], BaseException]) -> tuple[int, ...]:
        # the first error in the order of the data's keys; a section's unknown keys before its values
        rank, node = [], data
        for k in pe[0][len(prefix):]:
            rank.append(list(node).index(k) if isinstance(node, dict) and k in node else len(node or ()))
            node = node.get(k) if isinstance(node, dict) else None
        return (*rank, -1 if isinstance(pe[1], cattrs.ForbiddenExtraKeysError) else 0)

    path, err = min(found, key=order)
    if isinstance(err, cattrs.ForbiddenExtraKeysError):
        raise ConfigError(
            f"unknown configuration key(s): {', '.join('.'.join(path + (k,)) for k in sorted(err.extra_fields))}"
        )
    if isinstance(err, _BadValue):
        raise ConfigError(f"'{'.'.join(path)}' {err}")
    raise err  # a section's own check (ConfigError naming the key) or a bug


def load_config(path: str | Path | None = None) -> Config:
    """Load a YAML configuration; ``None`` gives the defaults."""
    if path is None:
        return Config()
    p = Path(path)
    if not p.is_file():
        raise ConfigError("configuration file not found", p)
    try:
        text = p.read_text()
        if text.lstrip().startswith("%YAML"):
            # OpenCV FileStorage header (ORB-SLAM2 settings files) is not plain YAML.
            text = "\n".join(line for line in text.splitlines() if not line.startswith("%YAML"))
        data = yaml.safe_load(text) or {}
    except yaml.YAMLError as e:
        raise ConfigError(f"cannot parse YAML: {yaml_error_line(e)}", p) from None
    except OSError as e:
        raise ConfigError(f"cannot read the file: {e.strerror or e}", p) from None
    dup = duplicate_key(text)
    if dup is not None:
        raise ConfigError(f"line {dup[1]}: key '{dup[0]}' is given twice (which one is meant?)", p)
    if not isinstance(data, dict):
        raise ConfigError("top level must be a mapping", p)
    # ORB-SLAM2 settings files have flat dotted keys ("Camera.fx"); they carry no
    # dynastereo sections, so keep only our sections here (calibration is read by io),
    # except the SLAM parameters ORB-SLAM2 shares with us (orbslam2_slam_values).
    ours = {k: v for k, v in data.items() if "." not in k and k not in ORBSLAM2_SLAM_KEYS}
    theirs = orbslam2_slam_values(data, p)
    if theirs:
        slam = ours.get("slam") or {}
        if not isinstance(slam, dict):
            raise ConfigError("'slam' must be a mapping", p)
        ours["slam"] = {**theirs, **slam}  # an explicit slam: section wins
    try:
        return from_dict(Config, ours)
    except ConfigError as e:
        raise ConfigError(str(e), p) from None


def dump_config(cfg: Config, path: str | Path | None = None) -> str:
    text = yaml.safe_dump(to_dict(cfg), sort_keys=False)
    if path is not None:
        Path(path).write_text(text)
    return text
