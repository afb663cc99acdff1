"""The configuration: every section validates itself where it is made or loaded, the
error names the key (and the file), and the ORB-SLAM2 settings adapter is one."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from dynastereo.cli.main import app
from dynastereo.config import Config, SlamConfig, load_config, orbslam2_slam_values
from dynastereo.errors import ConfigError
from dynastereo.slam.settings import slam_config_from_orbslam

runner = CliRunner()


@pytest.mark.parametrize("key,value", [
    ("slam.local_ba", "bogus"),
    ("slam.n_features", -5),
    ("slam.ba_iterations", 0),
    ("slam.loop_max_verify", 0),
    ("stereo.block_size", 16),
    ("stereo.algorithm", "magic"),
    ("stereo.region", "half"),
    ("stereo.wls", "yes"),  # only true / false (or a YAML boolean) is a boolean
    ("detector.canvas", "square"),
    ("detector.threads", 0),
    ("masker.kind", "magic"),
    ("masker.box_margin", -1),
    ("masker.outline.transfer", "warp"),
    ("masker.outline.min_outline_fraction", 1.5),
    ("masker.outline.dilate", -2),
    ("seed", -1),
    ("slam.n_features", "nan"),  # an integer key given nan/inf: one line, not a bare OverflowError
    ("seed", float("inf")),
])
def test_a_bad_value_is_refused_naming_the_key(key: str, value) -> None:
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        Config().with_overrides({key: value})


def test_choices_and_booleans_accept_what_a_command_line_gives() -> None:
    cfg = Config().with_overrides({"stereo.algorithm": "SGBM", "stereo.wls": "true", "slam.local_ba": "inline",
                                   "stereo.block_size": "9"})
    assert (cfg.stereo.algorithm, cfg.stereo.wls, cfg.slam.local_ba, cfg.stereo.block_size) == ("sgbm", True, "inline", 9)


def test_a_configuration_changed_after_it_was_made_is_checked_by_its_user() -> None:
    import numpy as np

    from dynastereo.slam import System
    from dynastereo.datatypes import StereoCalibration

    cfg = Config()
    cfg.slam.local_ba = "bogus"
    with pytest.raises(ConfigError, match="slam.local_ba"):
        System(cfg, StereoCalibration(np.array([[500.0, 0, 320], [0, 500.0, 96], [0, 0, 1]]), 0.5, 640, 192))
    with pytest.raises(ConfigError, match="slam.local_ba"):
        cfg.validate()


def test_config_command_fails_on_a_value_out_of_range_naming_file_and_key(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("stereo:\n  block_size: 16\n")
    r = runner.invoke(app, ["config", str(bad)])
    assert r.exit_code == 2 and "bad.yaml" in r.output and "stereo.block_size" in r.output
    assert "Traceback" not in r.output
    bad.write_text("slam:\n  n_features: -5\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml.*slam\.n_features"):
        load_config(bad)


def test_one_orbslam2_adapter_for_config_files_and_settings(tmp_path: Path) -> None:
    settings = {"ORBextractor.nFeatures": 1200, "ORBextractor.scaleFactor": 1.3, "ThDepth": 40.0, "Camera.fps": 20.0}
    values = orbslam2_slam_values(settings)
    assert values == {"n_features": 1200, "scale_factor": 1.3, "th_depth": 40.0, "max_frames": 20}
    p = tmp_path / "orb.yaml"
    p.write_text("%YAML:1.0\n" + "".join(f"{k}: {v}\n" for k, v in settings.items()))
    from_file = load_config(p).slam
    from_settings = slam_config_from_orbslam(settings, SlamConfig())
    for k, v in values.items():
        assert getattr(from_file, k) == getattr(from_settings, k) == v
    with pytest.raises(ConfigError, match="ORBextractor.nFeatures"):
        orbslam2_slam_values({"ORBextractor.nFeatures": 1000.5}, p)
