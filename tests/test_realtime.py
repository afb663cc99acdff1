"""The real-time settings (docs/architecture.md, "Real time: who runs where"): library threads that do not
steal the tracking's core, and the hot kernels rewritten for speed giving the same numbers."""

from __future__ import annotations

from pathlib import Path

from conftest import require
from dynastereo.masking.detection.onnx import make_session


def test_onnxruntime_threads_do_not_spin(models_dir: Path):
    # onnxruntime's intra-op workers busy-wait between ops by default: on two cores that
    # spinning took ~30 ms of CPU a frame from the tracking (KITTI 03: 7.9 -> 9.9 FPS)
    model = require(models_dir / "yolox-nano" / "yolox_nano.onnx", "YOLOX-nano model")
    opts = make_session(model, 2).get_session_options()
    assert opts.intra_op_num_threads == 2
    assert opts.get_session_config_entry("session.intra_op.allow_spinning") == "0"
    assert opts.get_session_config_entry("session.inter_op.allow_spinning") == "0"
