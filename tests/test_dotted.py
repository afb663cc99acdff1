"""Dotted keys: flatten_dotted / nest_dotted and their users (config overrides, ROS params)."""

from __future__ import annotations

import pytest

from dynastereo.config import Config, to_dict
from dynastereo.dotted import flatten_dotted, nest_dotted
from dynastereo.errors import ConfigError


def test_flatten_dotted_descends_dicts_only_and_keeps_order() -> None:
    d = {"a": {"b": 1, "c": {"d": [1, 2]}}, "e": None, 3: "x", "f": {}}
    assert list(flatten_dotted(d).items()) == [("a.b", 1), ("a.c.d", [1, 2]), ("e", None), ("3", "x")]
    assert flatten_dotted(d, skip_none=True) == {"a.b": 1, "a.c.d": [1, 2], "3": "x"}
    assert flatten_dotted({"wls": True, "p1": None}, "stereo") == {"stereo.wls": True, "stereo.p1": None}
    assert flatten_dotted(5) == {"": 5} and flatten_dotted(5, "k") == {"k": 5}


def test_nest_dotted_inverts_flatten() -> None:
    d = {"a": {"b": 1, "c": {"d": [1, 2]}}, "e": "x"}
    assert nest_dotted(flatten_dotted(d)) == d
    into = {"a": {"b": 0}}
    assert nest_dotted({"a.b": 2, "z.y": 3}, into) is into and into == {"a": {"b": 2}, "z": {"y": 3}}


@pytest.mark.parametrize("key", ["stereo.nope", "nope.wls", "stereo.wls.deeper", "nope"])
def test_nest_dotted_known_only_refuses_unknown_keys(key: str) -> None:
    data = {"stereo": {"wls": False}, "seed": 0}
    with pytest.raises(KeyError) as e:
        nest_dotted({"seed": 1, key: 1, "other.bad": 2}, data, known_only=True)
    assert e.value.args[0] == key  # the first unknown key in order


def test_with_overrides_names_the_unknown_key_and_skips_none() -> None:
    with pytest.raises(ConfigError, match=r"unknown configuration key 'stereo\.nope'"):
        Config().with_overrides({"stereo.wls": True, "stereo.nope": 1})
    cfg = Config().with_overrides({"stereo.wls": True, "stereo.block_size": None, "masker.outline.dilate": 3})
    assert (cfg.stereo.wls, cfg.stereo.block_size, cfg.masker.outline.dilate) == (True, 15, 3)


def test_ros_parameter_dict_leaves_out_none_as_before() -> None:
    from dynastereo.ros.ros1 import _nested

    def old(d):  # the node's former hand-written version
        return {k: old(v) if isinstance(v, dict) else v for k, v in d.items() if v is not None}

    d = to_dict(Config().with_overrides({"stereo.p1": None, "stereo.wls": True}))
    assert d["stereo"]["p1"] is None
    got = _nested(d)
    assert got == old(d) and "p1" not in got["stereo"]
    assert list(got) == list(old(d)) and list(got["masker"]) == list(old(d)["masker"])


def test_ros_node_config_from_params_flattens_each_section() -> None:
    from dynastereo.ros.ros1 import config_from_params

    class FakeRospy:
        params = {"~stereo": {"wls": True, "p1": None}, "~masker": {"outline": {"dilate": 4}}, "~seed": 7,
                  "~slam": "not a dict", "~objects": {"block_size": 11}}

        def get_param(self, name, default=None):
            return self.params.get(name, default)

        def has_param(self, name):
            return name in self.params

    cfg = config_from_params(FakeRospy())
    assert (cfg.stereo.wls, cfg.stereo.p1, cfg.masker.outline.dilate, cfg.seed) == (True, None, 4, 7)
    assert cfg.objects.block_size == 11
