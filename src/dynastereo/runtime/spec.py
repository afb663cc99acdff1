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
from typing import Any, Protocol, runtime_checkable

from ..config import Config
from ..errors import ConfigError
from ..io.calib import is_orbslam2_settings, read_yaml_file

class JobKind(StrEnum):
    MASK = "mask"  # masks only (``dynastereo mask``)
    RUN = "run"  # masks + SLAM (``dynastereo run``)


def settings_calibration(config: str | Path | None) -> Path | None:
    """``config`` when it is an ORB-SLAM2 settings file, else None: the calibration of a bag
    that has no CameraInfo (``run --bag IN.bag --config settings.yaml``)."""
    if config is None or not is_orbslam2_settings(read_yaml_file(config)):
        return None
    return Path(config)


def settings_disagreement(config: str | Path | None, calibration: Any, calib_file: Any = None) -> str | None:
    """A one-line warning when ``config`` is an ORB-SLAM2 settings file whose camera
    (``Camera.fx``, ``Camera.bf``) disagrees (by more than 1 %) with the sequence's own
    ``calibration`` -- which is the one used -- else None."""
    if config is None or calibration is None:
        return None
    try:
        s = read_yaml_file(config)
        if not is_orbslam2_settings(s):
            return None
        from ..io.calib import load_orbslam2_settings

        s = load_orbslam2_settings(config)
        fx, bf = float(s["Camera.fx"]), float(s["Camera.bf"])
    except (KeyError, TypeError, ValueError, ConfigError, OSError):
        return None
    except Exception:  # noqa: BLE001 -- an unreadable settings file is the configuration loader's to report
        return None
    if not (fx > 0 and bf > 0):
        return None
    own_fx, own_b = float(calibration.K[0, 0]), float(calibration.baseline)
    b = bf / fx
    if abs(fx - own_fx) <= 0.01 * own_fx and abs(b - own_b) <= 0.01 * own_b:
        return None
    src = f" ({calib_file})" if calib_file else ""
    return (f"{config}: its camera (Camera.fx {fx:g} px, Camera.bf {bf:g}: baseline {b:.4g} m) disagrees with the "
            f"sequence's calibration{src} (fx {own_fx:g} px, baseline {own_b:.4g} m); the sequence's is used "
            "(--calib FILE chooses another)")


@runtime_checkable
class OpenableSource(Protocol):
    """A source that opens itself and may write outputs of its own beside the job's: a
    stereo ROS bag (:class:`dynastereo.ros.bagrun.BagSource`, ``run --bag``).  The runtime
    treats it as any other sequence: it opens it, reads its frames, and gives the
    observers it asks for (``job_observers``) the job's frames like every observer."""

    path: Path  # what it reads (for messages and run.json)
    kind: str  # a word for it ("bag"): the viewer's recording name

    def check(self, source: "SourceSpec") -> None:
        """Refuse source options that do not apply to it (a ConfigError)."""

    def check_job(self, job: "JobSpec") -> None:
        """Refuse job options that do not apply to it (a ConfigError)."""

    def open(self, calib: Path | None) -> Any:
        """The :class:`~dynastereo.io.base.Sequence` to read (``calib``: a YAML calibration
        that wins over the source's own)."""

    def job_observers(self, job: "JobSpec", sequence: Any) -> tuple[Any, ...]:
        """Observers of the job's frames that write the source's own outputs (each an
        :class:`~dynastereo.observers.OutputObserver`: opened once the output folder is
        ready, closed after the job's last files)."""


@dataclass(frozen=True)
class SourceSpec:
    """Exactly one of: ``path`` (a sequence folder, a stereo video ``stereo.mkv`` or
    ``left.mkv,right.mkv``, a camera ``cam:N``), ``opener`` (a source that opens itself:
    :class:`OpenableSource`, a ROS bag), or ``sequence`` (an opened
    :class:`~dynastereo.io.base.Sequence`, from the Python API)."""

    path: str | Path | None = None
    calib: Path | None = None  # YAML calibration (a generic folder, a video; a bag: wins over CameraInfo)
    rate: float | None = None  # Hz, for a folder without stamps
    color: bool | None = None
    opener: OpenableSource | None = None
    sequence: Any = None

    def __post_init__(self) -> None:
        given = sum(x is not None for x in (self.path, self.opener, self.sequence))
        if given != 1:
            raise ConfigError("give either a SEQUENCE folder or --bag FILE (not both)")
        if self.opener is not None:
            self.opener.check(self)
        if self.rate is not None:
            from ..errors import InputError
            from ..io.times import check_rate

            try:
                check_rate(self.rate)
            except InputError as e:
                raise ConfigError(str(e)) from None

    @property
    def name(self) -> str | None:
        """The input's path as a string (for run.json), when it has one."""
        if self.opener is not None:
            return str(self.opener.path)
        p = self.path if self.path is not None else getattr(self.sequence, "path", None)
        return None if p is None else str(p)


@dataclass(frozen=True)
class OutputSpec:
    """Where the results go and which are written (docs/guide/outputs.md)."""

    dir: Path
    overwrite: bool = True  # clear an earlier run's outputs there (False: refuse)
    save_masks: bool = False  # DIR/masks/{left,right}/NNNNNN.png (a run: the masks SLAM got)
    save_disparity: bool = False  # mask jobs: DIR/disparity/NNNNNN.png
    overlays: bool = False  # mask jobs: DIR/overlays/NNNNNN.png
    save_map: Path | None = None
    save_cloud: Path | None = None  # the final map's points as PLY, none on a mover
    report: bool = False  # DIR/report.html
    viewer: bool = False  # spawn the rerun viewer
    rrd: Path | None = None  # record for rerun

    def __post_init__(self) -> None:
        object.__setattr__(self, "dir", Path(self.dir))


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
    settings: Path | None = None  # the --config file: an ORB-SLAM2 one's camera is compared with the sequence's

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", JobKind(self.kind))
        o = self.outputs
        if self.localize_only and self.load_map is None:
            raise ConfigError("--localize-only needs --load-map FILE (localization needs a map)")
        if self.source.opener is not None:
            self.source.opener.check_job(self)
        if self.kind is JobKind.MASK:
            extra = [n for n, v in (("save_map", o.save_map), ("save_cloud", o.save_cloud), ("load_map", self.load_map))
                     if v]
            if extra:
                raise ConfigError(f"a mask job tracks nothing: {', '.join(extra)} need a run")
        elif o.save_disparity or o.overlays:
            raise ConfigError("--save-disparity / --overlays are outputs of `dynastereo mask`")
        if o.save_disparity and self.config.stereo.region != "full":  # the full frame's disparity is written
            object.__setattr__(self, "config", self.config.with_overrides({"stereo.region": "full"}))

    def with_(self, **changes: Any) -> "JobSpec":
        """A copy with ``changes`` (validated again)."""
        return replace(self, **changes)
