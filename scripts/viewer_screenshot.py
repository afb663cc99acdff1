"""README's viewer screenshot: a recording (``run --rrd``) opened in rerun's web viewer,
served by ``rerun --web-viewer`` and drawn by headless Chromium with software WebGL
(SwiftShader; no display, no GPU), then scaled down into a small PNG.

    python scripts/viewer_screenshot.py RUN.rrd docs/viewer.png [--settle 25] [--scale 0.8]

Needs ``pip install 'dynastereo[viz]'`` and Debian's ``chromium``.
"""

from __future__ import annotations

import argparse
import socket
import subprocess
import sys
import time
import urllib.parse
import urllib.request
from pathlib import Path

import cv2
import numpy as np

from dynastereo.viz.browser import load_page


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait_http(url: str, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            urllib.request.urlopen(url, timeout=2).close()
            return
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.3)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rrd", type=Path)
    ap.add_argument("png", type=Path)
    ap.add_argument("--settle", type=float, default=25.0, help="seconds for the viewer to load and draw")
    ap.add_argument("--scale", type=float, default=0.8)
    a = ap.parse_args()
    web, grpc = _free_port(), _free_port()
    rerun = Path(sys.executable).with_name("rerun")
    proc = subprocess.Popen([str(rerun), str(a.rrd), "--web-viewer", "--web-viewer-port", str(web), "--port",
                             str(grpc), "--renderer", "webgl"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        base = f"http://127.0.0.1:{web}/"
        _wait_http(base, 30)
        source = urllib.parse.quote(f"rerun+http://localhost:{grpc}/proxy", safe="")
        page = load_page(f"{base}?url={source}&renderer=webgl", width=1400, height=820, settle_s=a.settle,
                         webgl=True, timeout_s=a.settle + 60)
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    img = cv2.imdecode(np.frombuffer(page.screenshot, np.uint8), cv2.IMREAD_COLOR)
    img = cv2.resize(img, None, fx=a.scale, fy=a.scale, interpolation=cv2.INTER_AREA)
    z = img.reshape(-1, 3).astype(np.float32)  # a 64-colour palette keeps the PNG small
    _, labels, centres = cv2.kmeans(z, 64, None, (cv2.TERM_CRITERIA_MAX_ITER, 8, 1.0), 1, cv2.KMEANS_PP_CENTERS)
    img = centres.astype(np.uint8)[labels.ravel()].reshape(img.shape)
    cv2.imwrite(str(a.png), img, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"{a.png}: {img.shape[1]}x{img.shape[0]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
