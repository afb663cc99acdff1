"""README's report screenshot: load a report in headless Chromium (dynastereo.viz.browser),
keep the top of the page, scale it down, write a small PNG.

    python scripts/report_screenshot.py RUN_DIR/report.html docs/report.png [--top 2400] [--scale 0.5]
"""

from __future__ import annotations

import argparse
import sys

import cv2
import numpy as np

from dynastereo.viz.browser import load_page


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("html")
    ap.add_argument("png")
    ap.add_argument("--top", type=int, default=2400, help="page pixels kept from the top")
    ap.add_argument("--scale", type=float, default=0.5)
    a = ap.parse_args()
    page = load_page(a.html)
    if page.errors:
        print("page errors:", *page.errors, sep="\n  ", file=sys.stderr)
        return 1
    img = cv2.imdecode(np.frombuffer(page.screenshot, np.uint8), cv2.IMREAD_COLOR)[: a.top]
    img = cv2.resize(img, None, fx=a.scale, fy=a.scale, interpolation=cv2.INTER_AREA)
    # a 64-colour palette keeps the PNG small (plots and tables are flat colours)
    z = img.reshape(-1, 3).astype(np.float32)
    _, labels, centres = cv2.kmeans(z, 64, None, (cv2.TERM_CRITERIA_MAX_ITER, 8, 1.0), 1, cv2.KMEANS_PP_CENTERS)
    img = centres.astype(np.uint8)[labels.ravel()].reshape(img.shape)
    cv2.imwrite(a.png, img, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"{a.png}: {img.shape[1]}x{img.shape[0]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
