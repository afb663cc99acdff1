#!/usr/bin/env bash
# Create or reuse .venv in the repository root and install dynastereo into it (editable).
# Re-installs only when pyproject.toml changed.  Uses Debian's /usr/bin/python3 with
# --system-site-packages when available, so the ROS 1 packages from apt are importable too.
set -euo pipefail
cd "$(dirname "$0")/.."

if [ ! -x .venv/bin/python ]; then
    if [ -x /usr/bin/python3 ] && /usr/bin/python3 -c 'import venv, ensurepip' 2>/dev/null; then
        /usr/bin/python3 -m venv --system-site-packages .venv
    else
        python3 -m venv .venv
    fi
fi

stamp=.venv/.dynastereo-installed
want=$(sha256sum pyproject.toml | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ] || ! .venv/bin/python -c 'import dynastereo' 2>/dev/null; then
    echo "[venv] installing dynastereo and its dependencies into .venv ..." >&2
    .venv/bin/python -m pip install --quiet --upgrade pip >/dev/null 2>&1 || true
    .venv/bin/python -m pip install --quiet -e ".[test,viz,bench,openvino,docs,ros2]"
    echo "$want" > "$stamp"
fi
