"""Synthetic stereo street sequences with independently moving objects and exact ground truth.

``generate(out, scenario)`` renders a KITTI-odometry folder (``out/sequences/00`` with
``image_0``, ``image_1``, ``calib.txt``, ``times.txt``; ``out/poses/00.txt``) plus
``sequences/00/gt/``: left disparity (uint16 x256), left/right instance masks and
``objects.json``.  Scenes are ray cast analytically (vectorized numpy; exact pinhole
stereo with a z-buffer), so the right image is the left one warped by the disparity on
non-occluded pixels.  ``OracleDetector`` returns the ground-truth boxes of a frame (for
testing masking and SLAM without a network).

Modules: ``world`` (city, textures), ``objects`` (shapes, motions), ``scenarios``
(the drives), ``render`` (ray casting), ``writer`` (files), ``oracle`` (GT readers).
"""

from .oracle import GTObject, OracleDetector, SynthGroundTruth, read_gt_disparity, read_gt_masks, read_objects
from .scenarios import SCENARIOS, Plan, Scenario, make_plan
from .writer import BASELINE, DEFAULT_NOISE, DEFAULT_SIZE, generate, intrinsics, parse_size

__all__ = [
    "generate",
    "SCENARIOS",
    "Scenario",
    "Plan",
    "make_plan",
    "OracleDetector",
    "GTObject",
    "SynthGroundTruth",
    "read_objects",
    "read_gt_masks",
    "read_gt_disparity",
    "intrinsics",
    "parse_size",
    "BASELINE",
    "DEFAULT_NOISE",
    "DEFAULT_SIZE",
]
