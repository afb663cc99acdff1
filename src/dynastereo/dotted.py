"""Nested dicts <-> flat dotted keys (``{"stereo": {"wls": True}}`` <-> ``{"stereo.wls": True}``).

The one implementation behind ``Config.with_overrides``, the ROS node's parameters and the
run report's settings table.
"""

from __future__ import annotations

from typing import Any

__all__ = ["flatten_dotted", "nest_dotted"]


def flatten_dotted(d: Any, prefix: str = "", *, skip_none: bool = False) -> dict[str, Any]:
    """``{"a": {"b": 1}, "c": 2}`` -> ``{"a.b": 1, "c": 2}`` (keys prefixed ``prefix.``).

    Only dicts are descended into (lists and other values are leaves, as they are); an empty
    dict gives no key.  ``skip_none`` leaves out None values.  A ``d`` that is not a dict is
    one leaf under ``prefix`` (``{"": d}`` without a prefix)."""
    out: dict[str, Any] = {}

    def walk(key: str, v: Any) -> None:
        if isinstance(v, dict):
            for k, vv in v.items():
                walk(f"{key}.{k}" if key else str(k), vv)
        elif v is not None or not skip_none:
            out[key] = v

    walk(prefix, d)
    return out


def nest_dotted(flat: dict[str, Any], into: dict[str, Any] | None = None, *,
                known_only: bool = False) -> dict[str, Any]:
    """``{"a.b": 1, "c": 2}`` -> ``{"a": {"b": 1}, "c": 2}``, set into ``into`` (a new dict
    when None) and returned.  With ``known_only`` every dotted key must already exist in
    ``into`` (each part but the last a dict): ``KeyError(dotted key)`` otherwise, raised at
    the first unknown key in ``flat``'s order."""
    out: dict[str, Any] = {} if into is None else into
    for dotted, value in flat.items():
        node = out
        parts = dotted.split(".")
        for p in parts[:-1]:
            if p not in node or not isinstance(node[p], dict):
                if known_only:
                    raise KeyError(dotted)
                node[p] = {}
            node = node[p]
        if known_only and parts[-1] not in node:
            raise KeyError(dotted)
        node[parts[-1]] = value
    return out
