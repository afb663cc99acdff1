"""ROS interface: offline bags (no ROS installation needed) and a live ROS 1 node.

* :mod:`.convert` -- numpy <-> message conversions (images, CameraInfo, poses); no cv_bridge.
* :mod:`.messages` -- the output messages and topic names, for any message library.
* :mod:`.bags` -- ROS 1 ``.bag`` / ROS 2 ``.db3`` / ``.mcap`` reading (:class:`BagStereoSequence`),
  writing (:class:`BagWriter`) and :func:`export_bag` (a sequence folder as a bag).
* :mod:`.bagrun` -- :class:`BagOutput`, what ``dynastereo run --bag`` writes into its output bag.
* :mod:`.core` -- :class:`StereoNodeCore`, the node's transport-agnostic logic.
* :mod:`.ros1` -- the ``rospy`` adapter (``dynastereo_node``), :mod:`.player` -- a sequence
  published as live topics.  Both need ROS 1 (Debian: ``python3-rospy`` ...).
* :mod:`.ros2` -- the ROS 2 node over DDS without rclpy (``dynastereo node --ros2``),
  :mod:`.ros2_player` -- ``dynastereo play --ros2``, :mod:`.dds` -- ROS 2's wire types,
  codecs and QoS over Cyclone DDS (the ``ros2`` extra).

Nothing here imports ``rospy`` or ``cyclonedds`` at import time; only :mod:`.ros1` and
:mod:`.player` need the first, :mod:`.ros2` / :mod:`.ros2_player` the second.
"""

from __future__ import annotations

from .bagrun import BAG_OUTPUTS, BagOutput, BagSource, parse_bag_outputs
from .bags import BAG_FORMATS, BagStereoSequence, BagWriter, ExportResult, bag_format, bag_topics, export_bag, \
    read_messages, read_odometry
from .convert import ImageDecoder, calibration_from_camera_info, camera_info_fields, image_fields
from .core import DropOldestQueue, NodeResult, NodeSink, StereoInput, StereoNodeCore
from .messages import (
    DEFAULT_LEFT_INFO,
    DEFAULT_LEFT_TOPIC,
    DEFAULT_RIGHT_INFO,
    DEFAULT_RIGHT_TOPIC,
    OUTPUT_TOPICS,
    DisparityData,
    OdometryData,
)

__all__ = [
    "BAG_OUTPUTS",
    "BagOutput",
    "BagSource",
    "BAG_FORMATS",
    "BagStereoSequence",
    "BagWriter",
    "DEFAULT_LEFT_INFO",
    "DEFAULT_LEFT_TOPIC",
    "DEFAULT_RIGHT_INFO",
    "DEFAULT_RIGHT_TOPIC",
    "DisparityData",
    "DropOldestQueue",
    "ExportResult",
    "ImageDecoder",
    "NodeResult",
    "NodeSink",
    "OUTPUT_TOPICS",
    "OdometryData",
    "StereoInput",
    "StereoNodeCore",
    "bag_format",
    "bag_topics",
    "calibration_from_camera_info",
    "camera_info_fields",
    "export_bag",
    "image_fields",
    "parse_bag_outputs",
    "read_messages",
    "read_odometry",
]
