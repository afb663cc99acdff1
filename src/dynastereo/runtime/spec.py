"""What a job is, validated once: :class:`JobSpec` (source, configuration, outputs, options).

Every entry point -- ``dynastereo mask`` / ``run`` (folder, video, camera, bag), the
Python API, the benchmarks, the demo -- builds a :class:`JobSpec` and hands it to
:func:`dynastereo.runtime.run`; none assembles a pipeline itself.  The checks that need
no file are made here, when the spec is built (a bad combination of options fails before
anything is opened); those that need the input (frames, the stereo pair, the model) are
made by the runtime before the first frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from enum import StrEnum
from pathlib import Path
from typing import Any

from ..config import Config
from ..errors import ConfigError
from ..io.calib import is_orbslam2_settings, read_yaml_file

DEFAULT_LEFT_TOPIC = "/camera/left/image_raw"
DEFAULT_RIGHT_TOPIC = "/camera/right/image_raw"
#: What a bag run can write into its output bag (``--bag-outputs``).
BAG_OUTPUTS = ("odometry", "tf", "masked", "masks", "disparity", "path", "map_points", "objects")


class JobKind(StrEnum):
    MASK = "mask"  # masks only (``dynastereo mask``)
    RUN = "run"  # masks + SLAM (``dynastereo run``)


def parse_bag_outputs(spec: str | list[str] | tuple[str, ...] | None) -> tuple[str, ...]:
    """``"all"`` / None -> every output; else a comma list of :data:`BAG_OUTPUTS`."""
    if spec is None:
        return BAG_OUTPUTS
    items = [s.strip() for s in (spec.split(",") if isinstance(spec, str) else spec) if s.strip()]
    if items == ["all"]:
        return BAG_OUTPUTS
    bad = [s for s in items if s not in BAG_OUTPUTS]
    if bad:
        from ..errors import InputError

        raise InputError(f"unknown bag output(s) {', '.join(bad)}; choose from {', '.join(BAG_OUTPUTS)} or 'all'")
    return tuple(items)


def settings_calibration(config: str | Path | None) -> Path | None:
    """``config`` when it is an ORB-SLAM2 settings file, else None: the calibration of a bag
    that has no CameraInfo (``run --bag IN.bag --config settings.yaml``)."""
    if config is None or not is_orbslam2_settings(read_yaml_file(config)):
        return None
    return Path(config)


@dataclass(frozen=True)
class BagSpec:
    """A stereo ROS bag as input (``run --bag``): topics, CameraInfo, pairing, rectification,
    and what goes into the output bag (``DIR/output.<same format>``)."""

    path: Path
    left_topic: str = DEFAULT_LEFT_TOPIC
    right_topic: str = DEFAULT_RIGHT_TOPIC
    left_info: str | None = "auto"  # auto: camera_info beside the image topic; None: ignore
    right_info: str | None = "auto"
    tolerance_s: float = 0.005  # largest left/right stamp difference of a pair
    rectify: str = "auto"  # auto | yes | no
    fallback_calib: Path | None = None  # used only without CameraInfo (an ORB-SLAM2 settings file)
    outputs: tuple[str, ...] = BAG_OUTPUTS

    def __post_init__(self) -> None:
        if not self.tolerance_s >= 0:
            raise ConfigError(f"--sync-tolerance must be a time >= 0 ms (milliseconds), got {self.tolerance_s * 1e3:g}")
        if self.rectify not in ("auto", "yes", "no"):
            raise ConfigError(f"--rectify must be auto, yes or no, got {self.rectify!r}")
        object.__setattr__(self, "path", Path(self.path))
        object.__setattr__(self, "outputs", parse_bag_outputs(self.outputs))


@dataclass(frozen=True)
class SourceSpec:
    """Exactly one of: ``path`` (a sequence folder, a stereo video ``stereo.mkv`` or
    ``left.mkv,right.mkv``, a camera ``cam:N``), ``bag``, or ``sequence`` (an opened
    :class:`~dynastereo.io.base.Sequence`, from the Python API)."""

    path: str | Path | None = None
    calib: Path | None = None  # YAML calibration (a generic folder, a video; a bag: wins over CameraInfo)
    rate: float | None = None  # Hz, for a folder without stamps
    color: bool | None = None
    bag: BagSpec | None = None
    sequence: Any = None

    def __post_init__(self) -> None:
        given = sum(x is not None for x in (self.path, self.bag, self.sequence))
        if given != 1:
            raise ConfigError("give either a SEQUENCE folder or --bag FILE (not both)")
        if self.bag is not None and self.rate is not None:
            raise ConfigError("--rate is for sequence folders; a bag's images carry their stamps")
        if self.rate is not None and not self.rate > 0:
            raise ConfigError(f"--rate must be a frame rate > 0 Hz, got {self.rate:g}")

    @property
    def name(self) -> str | None:
        """The input's path as a string (for run.json), when it has one."""
        if self.bag is not None:
            return str(self.bag.path)
        p = self.path if self.path is not None else getattr(self.sequence, "path", None)
        return None if p is None else str(p)


@dataclass(frozen=True)
class OutputSpec:
    """Where the results go and which are written (see README "Outputs")."""

    dir: Path
    overwrite: bool = True  # clear an earlier run's outputs there (False: refuse)
    save_masks: bool = False  # DIR/masks/{left,right}/NNNNNN.png (a run: the masks SLAM got)
    save_disparity: bool = False  # mask jobs: DIR/disparity/NNNNNN.png
    overlays: bool = False  # mask jobs: DIR/overlays/NNNNNN.png
    save_map: Path | None = None
    save_cloud: Path | None = None  # the final map's points as PLY, none on a mover
    save_mesh: Path | None = None  # the static world's dense mesh as PLY (mesh/), movers left out
    save_dense_cloud: Path | None = None  # the same fused surface's points, without triangles
    report: bool = False  # DIR/report.html
    viewer: bool = False  # spawn the rerun viewer
    rrd: Path | None = None  # record for rerun

    def __post_init__(self) -> None:
        object.__setattr__(self, "dir", Path(self.dir))

    @property
    def mesh_wanted(self) -> bool:
        return self.save_mesh is not None or self.save_dense_cloud is not None


@dataclass(frozen=True)
class JobSpec:
    """One job (module doc).  ``frames``: a count N or index ranges ``a-b,c-d`` (fed in that
    order); ``load_map`` / ``localize_only``: start from a saved map (and only localize in
    it); ``stereo_check``: refuse identical, swapped or unrectified pairs; ``gt``: ground
    truth for the report and the viewer (default: the sequence's own); ``prefetch``: mask
    frame k+1 on a second thread while frame k is tracked (same results either way)."""

    kind: JobKind
    source: SourceSpec
    outputs: OutputSpec
    config: Config = field(default_factory=Config)
    frames: str | int | None = None
    models_dir: Path | None = None
    load_map: Path | None = None
    localize_only: bool = False
    stereo_check: bool = True
    gt: Path | None = None
    prefetch: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", JobKind(self.kind))
        o = self.outputs
        if self.localize_only and self.load_map is None:
            raise ConfigError("--localize-only needs --load-map FILE (localization needs a map)")
        if self.source.bag is not None and (o.save_map or self.load_map):
            raise ConfigError("--save-map / --load-map work on sequence folders, not with --bag")
        if self.kind is JobKind.MASK:
            extra = [n for n, v in (("save_map", o.save_map), ("save_cloud", o.save_cloud), ("save_mesh", o.save_mesh),
                                    ("save_dense_cloud", o.save_dense_cloud), ("load_map", self.load_map),
                                    ("bag", self.source.bag)) if v]
            if extra:
                raise ConfigError(f"a mask job tracks nothing: {', '.join(extra)} need a run")
        elif o.save_disparity or o.overlays:
            raise ConfigError("--save-disparity / --overlays are outputs of `dynastereo mask`")
        if o.save_disparity and self.config.stereo.region != "full":  # the full frame's disparity is written
            object.__setattr__(self, "config", self.config.with_overrides({"stereo.region": "full"}))

    def with_(self, **changes: Any) -> "JobSpec":
        """A copy with ``changes`` (validated again)."""
        return replace(self, **changes)
