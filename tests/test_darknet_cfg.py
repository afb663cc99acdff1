"""One Darknet .cfg reader (models.sizecheck.darknet_cfg_sections) behind the detector's
[net] size and class count and the weights-size check."""

from __future__ import annotations

from pathlib import Path

import pytest

from conftest import require
from dynastereo.errors import ModelError
from dynastereo.masking.detection.darknet import count_yolo_classes, read_cfg_net
from dynastereo.models.sizecheck import darknet_cfg_sections

CFG = """# a comment
stray=1
[net]
Width = 320   # trailing comment
height=256
[convolutional]
filters=18
[yolo]
mask = 0,1
[region]
classes= 7
[yolo]
classes=80
[net]
channels=3
"""


def test_sections_in_order_lower_case_without_comments(tmp_path: Path) -> None:
    p = tmp_path / "a.cfg"
    p.write_text(CFG)
    secs = darknet_cfg_sections(p)
    assert [n for n, _ in secs] == ["net", "convolutional", "yolo", "region", "yolo", "net"]
    assert secs[0][1] == {"width": "320", "height": "256"} and secs[3][1] == {"classes": "7"}
    assert read_cfg_net(p) == {"width": "320", "height": "256", "channels": "3"}  # every [net] section
    assert count_yolo_classes(p) == 7  # the first [yolo]/[region] that has classes=


def test_classes_not_a_number_or_absent(tmp_path: Path) -> None:
    p = tmp_path / "b.cfg"
    p.write_text("[net]\nwidth=416\n[yolo]\nclasses=many\n[yolo]\nclasses=3\n")
    assert count_yolo_classes(p) is None
    p.write_text("[net]\nwidth=416\n")
    assert count_yolo_classes(p) is None
    with pytest.raises(ModelError, match="cannot read Darknet cfg"):
        read_cfg_net(tmp_path / "missing.cfg")


def test_the_real_yolov3_tiny_cfg(models_dir) -> None:
    cfg = require(models_dir / "yolov3-tiny" / "yolov3-tiny.cfg", "model yolov3-tiny")
    net = read_cfg_net(cfg)
    assert (int(net["width"]), int(net["height"])) == (416, 416) and count_yolo_classes(cfg) == 80
