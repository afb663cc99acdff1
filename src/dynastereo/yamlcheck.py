"""Duplicate keys in a YAML text: PyYAML (and OpenCV's FileStorage) keep the last of two
equal keys without a word, so ``baseline: 0.54`` followed later by ``baseline: 537`` would
silently win.  :func:`duplicate_key` finds the first such key (with its line), for the
configuration and calibration readers to refuse."""

from __future__ import annotations

import yaml


def duplicate_key(text: str) -> tuple[str, int] | None:
    """``(dotted key, line)`` of the first key given twice in one mapping of ``text``, or
    None (also None for text that does not compose as YAML: its reader reports that)."""
    lines = [ln for ln in text.splitlines() if not ln.startswith("%YAML")]  # OpenCV's header
    offset = len(text.splitlines()) - len(lines)
    try:
        root = yaml.compose("\n".join(lines), Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return None
    stack: list[tuple[yaml.Node, str]] = [(root, "")] if root is not None else []
    while stack:
        node, prefix = stack.pop()
        if isinstance(node, yaml.MappingNode):
            seen: set[str] = set()
            for k, v in node.value:
                name = str(k.value) if isinstance(k, yaml.ScalarNode) else repr(k.value)
                if name in seen:
                    return f"{prefix}{name}", k.start_mark.line + 1 + offset
                seen.add(name)
                stack.append((v, f"{prefix}{name}."))
        elif isinstance(node, yaml.SequenceNode):
            stack.extend((v, prefix) for v in node.value)
    return None


def yaml_error_line(e: yaml.YAMLError) -> str:
    """PyYAML's error in one line: ``line L, column C: problem (context)``.  PyYAML's own
    message spans several lines (a quoted snippet and a caret), which the one-line error
    rule would break."""
    mark = getattr(e, "problem_mark", None) or getattr(e, "context_mark", None)
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    problem = getattr(e, "problem", None)
    context = getattr(e, "context", None)
    if problem is None:
        lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
        return where + (lines[0] if lines else type(e).__name__)
    return where + problem + (f" ({context})" if context else "")
