"""The stereo SLAM on synthetic sequences with exact ground truth (``dynastereo.synth``).

Small sizes and short sequences keep this file fast; every sequence is deterministic
(seeded scene, seeded image noise) and the oracle (ground-truth) boxes stand in for a
detector, so the numbers do not depend on a network:

* ``static`` (nothing moves): the unmasked SLAM recovers the known motion;
* ``convoy`` (a box truck 4.5 m ahead at the rig's speed fills ~31 % of the view): the
  unmasked SLAM is pulled towards "standing still", masking the truck recovers the
  motion;
* ``crossing`` (the rig stands at a zebra while people and a crawling queue of cars
  and a truck cross in front): the unmasked SLAM "follows" the traffic, the masked one
  stands still.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dynastereo.api import run_sequence
from dynastereo.config import Config
from dynastereo.eval import evaluate_files, read_trajectory
from dynastereo.synth import generate, read_objects

SIZE = (480, 144)

pytestmark = pytest.mark.usefixtures("quiet_slam")


def _slam(seq: Path, out: Path, masker: str, frames: str | None = None):
    """(evaluation against the GT poses, JobResult) of one run with oracle boxes."""
    cfg = Config().with_overrides({"detector.name": "oracle", "masker.kind": masker})
    res = run_sequence(seq, out, cfg, frames=frames, save_masks=masker != "none")
    ev = evaluate_files(out / "trajectory.kitti.txt", seq.parent.parent / "poses" / "00.txt")
    return ev, res


def _path_length(poses: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())


@pytest.fixture(scope="module")
def static_seq(tmp_path_factory) -> Path:
    return generate(tmp_path_factory.mktemp("static"), "static", frames=40, seed=0, size=SIZE)


@pytest.fixture(scope="module")
def convoy_seq(tmp_path_factory) -> Path:
    return generate(tmp_path_factory.mktemp("convoy"), "convoy", frames=40, seed=0, size=SIZE)


@pytest.fixture(scope="module")
def crossing_seq(tmp_path_factory) -> Path:
    return generate(tmp_path_factory.mktemp("crossing"), "crossing", frames=75, seed=0, size=SIZE)


def test_slam_recovers_the_known_motion(static_seq: Path, tmp_path: Path):
    ev, res = _slam(static_seq, tmp_path / "run", "none")
    gt = read_trajectory(static_seq.parent.parent / "poses" / "00.txt").poses
    est = read_trajectory(tmp_path / "run" / "trajectory.kitti.txt").poses
    assert len(est) == len(gt) == 40 and not res.lost
    length = _path_length(gt)
    assert 30.0 < length < 40.0  # 9 m/s for 3.9 s
    # the absolute trajectory, after an SE(3) alignment: centimetres over ~35 m
    assert ev.ape["rmse"] < 0.15, ev.ape
    assert ev.drift_percent is not None and ev.drift_percent < 2.5, ev.drift_percent
    # without any alignment (world = first camera, as the GT): same path, same heading
    assert abs(_path_length(est) / length - 1.0) < 0.03
    assert np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3]) < 0.6
    R = est[-1, :3, :3].T @ gt[-1, :3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) < 1.5


def test_convoy_masking_helps(convoy_seq: Path, tmp_path: Path):
    gt_objects = read_objects(convoy_seq)
    lead = [o for f in gt_objects.frames for o in f if o.label == "truck" and o.moving]
    assert len(lead) == 40  # the truck is there all the time ...
    assert np.median([o.pixels_left for o in lead]) > 0.25 * SIZE[0] * SIZE[1]  # ... and big

    none, _ = _slam(convoy_seq, tmp_path / "none", "none")
    outline, res = _slam(convoy_seq, tmp_path / "outline", "outline")
    gt = read_trajectory(convoy_seq.parent.parent / "poses" / "00.txt").poses
    length = _path_length(gt)
    # unmasked: the truck's features (it keeps its distance) say "standing still"
    est_none = read_trajectory(tmp_path / "none" / "trajectory.kitti.txt").poses
    assert none.ape["rmse"] > 1.0, none.ape
    assert _path_length(est_none) < 0.7 * length
    # masked: the motion is recovered, the error is a small fraction of the unmasked one
    est = read_trajectory(tmp_path / "outline" / "trajectory.kitti.txt").poses
    assert outline.ape["rmse"] < 0.25, outline.ape
    assert abs(_path_length(est) / length - 1.0) < 0.05
    assert none.ape["rmse"] > 5.0 * outline.ape["rmse"]
    assert not res.lost
    # the masks written beside the trajectory cover the truck
    from dynastereo.eval.masks import score_mask_dir

    agree = score_mask_dir(tmp_path / "outline", convoy_seq)
    trucks = [s.iou for s in agree.scores if s.label == "truck"]
    assert trucks and np.median(trucks) > 0.6


def test_crossing_masking_keeps_the_waiting_rig_still(crossing_seq: Path, tmp_path: Path):
    """Frames 35-74: the rig brakes to the stop line and waits while a group of people
    and a queue of vehicles cross right in front of it."""
    gt_objects = read_objects(crossing_seq)
    moving = [sum(o.moving and o.distance < 20 for o in gt_objects.frame(i)) for i in range(35, 75)]
    assert min(moving) >= 2 and max(moving) >= 6
    P = read_trajectory(crossing_seq.parent.parent / "poses" / "00.txt").poses
    assert np.allclose(P[45, :3, 3], P[74, :3, 3])  # standing still
    none, _ = _slam(crossing_seq, tmp_path / "none", "none", frames="35-74")
    outline, res = _slam(crossing_seq, tmp_path / "outline", "outline", frames="35-74")
    assert none.ape["rmse"] > 1.0, none.ape  # it 'follows' the crossing traffic
    assert outline.ape["rmse"] < 0.5, outline.ape  # (perfect GT masks: ~0.27 m, the truck fills the view late on)
    assert none.ape["rmse"] > 4.0 * outline.ape["rmse"]
