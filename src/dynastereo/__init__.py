"""dynastereo: stereo visual SLAM in dynamic scenes, with fast dynamic-object masking.

Data flow: ``io`` (sequences, calibration, rectification) -> ``masking`` (disparity,
detector, outline, transfer) -> ``slam`` -> ``eval``; ``cli`` and ``ros`` are thin shells.
"""

__version__ = "0.1.0"

from .config import Config, load_config  # noqa: E402
from .errors import DynastereoError  # noqa: E402
from .datatypes import Detections, StereoCalibration, StereoFrame, StereoMasks  # noqa: E402

__all__ = [
    "Config",
    "load_config",
    "DynastereoError",
    "Detections",
    "StereoCalibration",
    "StereoFrame",
    "StereoMasks",
    "__version__",
]
