"""Shared fixtures: where the real data and models are, and how to skip without them.

``DYNASTEREO_DATA`` / ``DYNASTEREO_MODELS`` point at the shared data and models; unset,
they default to ``../shared/data`` and ``../shared/models`` beside the repository when
those exist (as ``.ci/run`` sets them).  When a test's files are absent it is skipped with
the reason -- unless ``DYNASTEREO_REQUIRE_DATA=1`` (CI), where it fails instead; so does
every other skip for something CI provides (:func:`skip_or_fail`: OpenVINO, a tmpfs).
"""

from __future__ import annotations

import logging

import os
from pathlib import Path

import pytest

REQUIRE = os.environ.get("DYNASTEREO_REQUIRE_DATA", "") not in ("", "0", "false", "no")
SHARED = Path(__file__).resolve().parents[1].parent / "shared"


def _default_shared() -> None:
    """``DYNASTEREO_DATA`` / ``DYNASTEREO_MODELS`` unset: ``../shared``'s, when it is there
    (set in the environment, so the CLI subprocesses of the tests see them too)."""
    for var, sub in (("DYNASTEREO_DATA", "data"), ("DYNASTEREO_MODELS", "models")):
        if not os.environ.get(var) and (SHARED / sub).is_dir():
            os.environ[var] = str(SHARED / sub)


_default_shared()


def skip_or_fail(reason: str) -> None:
    """Skip the test for ``reason`` -- or, under ``DYNASTEREO_REQUIRE_DATA=1`` (CI, which
    provides everything a test needs), fail it."""
    if REQUIRE:
        pytest.fail(reason + " [DYNASTEREO_REQUIRE_DATA=1]")
    pytest.skip(reason)


def require(path: Path | str | None, what: str = "") -> Path:
    """Return ``path`` if it exists; else skip (or fail under DYNASTEREO_REQUIRE_DATA=1)."""
    if path is not None and Path(path).exists():
        return Path(path)
    reason = f"missing {what or 'data'}: {path} (set DYNASTEREO_DATA / DYNASTEREO_MODELS)"
    if REQUIRE:
        pytest.fail(reason + " [DYNASTEREO_REQUIRE_DATA=1]")
    pytest.skip(reason)


def _env_dir(var: str) -> Path | None:
    v = os.environ.get(var)
    return Path(v) if v else None


@pytest.fixture(scope="session")
def data_dir() -> Path:
    return require(_env_dir("DYNASTEREO_DATA"), "DYNASTEREO_DATA")


@pytest.fixture(scope="session")
def models_dir() -> Path:
    return require(_env_dir("DYNASTEREO_MODELS"), "DYNASTEREO_MODELS")


@pytest.fixture(scope="session")
def kitti06(data_dir: Path) -> Path:
    return require(data_dir / "kitti_odometry/dataset/sequences/06", "KITTI seq 06")


@pytest.fixture(scope="session")
def kitti03(data_dir: Path) -> Path:
    return require(data_dir / "kitti_odometry/dataset/sequences/03", "KITTI seq 03")


@pytest.fixture(scope="session")
def euroc_dir(data_dir: Path) -> Path:
    return require(data_dir / "euroc/V1_01_easy_first40", "EuRoC V1_01_easy_first40")


@pytest.fixture
def quiet_slam():
    """The SLAM's WARNING lines (lost frames...) off for a test."""
    logging.getLogger("dynastereo").setLevel(logging.ERROR)
    yield
    logging.getLogger("dynastereo").setLevel(logging.NOTSET)


def track_offline(sequence: Path, models_dir: Path, n_frames: int):
    """The default configuration's SLAM on the first ``n_frames`` of a KITTI sequence
    folder, read straight from the folder (the reference the ROS paths must reproduce):
    the poses tracking returned per frame (``(n, 4, 4)``) and the shut-down ``System``."""
    import numpy as np

    from dynastereo.config import Config
    from dynastereo.io import KittiSequence
    from dynastereo.masking import build_masker
    from dynastereo.slam import System

    from dynastereo.objects.motion import build_motion
    from dynastereo.runtime.processor import apply_map_edits

    seq = KittiSequence(sequence)
    cfg = Config()
    masker = build_masker(cfg, seq.calibration, models_dir=models_dir)
    system = System(cfg, seq.calibration)
    motion = build_motion(cfg, seq.calibration, masker)  # the default: only what moves is masked
    poses = []
    for i in range(n_frames):
        f = seq.frame(i)
        masks = masker.mask(f)
        motion.measure(f, masks)
        res = system.track(f, motion.select(masks))
        motion.forgot(apply_map_edits(system, motion.update(masks, res).edits))
        poses.append(res.pose)
    system.shutdown()
    return np.array(poses), system


@pytest.fixture(autouse=True, scope="session")
def _private_checksum_cache(tmp_path_factory):
    """Model checksums verified at load are cached in a temp dir, not the user's ~/.cache."""
    mp = pytest.MonkeyPatch()
    mp.setenv("DYNASTEREO_CACHE_DIR", str(tmp_path_factory.mktemp("dynastereo-cache")))
    yield
    mp.undo()
