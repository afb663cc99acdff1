"""Input-layer timings: reading and rectifying stereo pairs.

Run: ``.venv/bin/python benchmarks/bench_io.py [--repeats 5]`` (needs DYNASTEREO_DATA).
Prints medians (ms per stereo pair) and writes ``benchmarks/results/io.json``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2

from _common import data_dir, machine, median_ms, results_path, write_json
from dynastereo.io import EurocSequence, Rectifier, open_sequence, read_image


def _median_ms(fn, items, repeats: int) -> float:
    return median_ms(fn, repeats, items)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=results_path("io"))
    args = ap.parse_args()
    data = data_dir()
    rows: list[dict] = []

    # --- EuRoC: raw 752x480 gray, rectified on read
    t0 = time.perf_counter()
    seq = open_sequence(data / "euroc/V1_01_easy_first40")
    open_ms = (time.perf_counter() - t0) * 1e3
    assert isinstance(seq, EurocSequence)
    pairs = [(read_image(l), read_image(r)) for l, r in zip(seq.left_paths, seq.right_paths)]
    idx = list(range(len(seq)))
    rect16 = seq.rectifier
    t0 = time.perf_counter()
    rect32 = Rectifier(seq.raw_calibration, map_type=cv2.CV_32FC1)
    build_ms = (time.perf_counter() - t0) * 1e3
    rows.append({"dataset": "euroc 752x480", "what": "open_sequence (csv, pairing, header checks, maps)",
                 "ms": open_ms, "per": "sequence"})
    rows.append({"dataset": "euroc 752x480", "what": "Rectifier build (stereoRectify + 2 maps)", "ms": build_ms,
                 "per": "sequence"})
    rows.append({"dataset": "euroc 752x480", "what": "read pair (2x imread png)",
                 "ms": _median_ms(lambda i: (read_image(seq.left_paths[i]), read_image(seq.right_paths[i])), idx,
                                  args.repeats), "per": "pair"})
    rows.append({"dataset": "euroc 752x480", "what": "rectify pair, CV_16SC2 maps (default)",
                 "ms": _median_ms(lambda p: rect16.rectify(*p), pairs, args.repeats), "per": "pair"})
    rows.append({"dataset": "euroc 752x480", "what": "rectify pair, CV_32FC1 maps",
                 "ms": _median_ms(lambda p: rect32.rectify(*p), pairs, args.repeats), "per": "pair"})
    rows.append({"dataset": "euroc 752x480", "what": "seq.frame(i) total (read + rectify)",
                 "ms": _median_ms(seq.frame, idx, args.repeats), "per": "pair"})

    # --- KITTI: already rectified
    for sid in ("03", "06"):
        kseq = open_sequence(data / f"kitti_odometry/dataset/sequences/{sid}")
        c = kseq.calibration
        rows.append({"dataset": f"kitti {sid} {c.width}x{c.height}", "what": "seq.frame(i) total (read only)",
                     "ms": _median_ms(kseq.frame, list(range(0, len(kseq), 3)), args.repeats), "per": "pair"})

    print(f"{'dataset':<22} {'what':<52} {'median ms':>10}  per")
    for r in rows:
        print(f"{r['dataset']:<22} {r['what']:<52} {r['ms']:>10.2f}  {r['per']}")
    write_json(args.out, {
        "benchmark": "io",
        "repeats": args.repeats,
        "machine": machine(opencv_threads=cv2.getNumThreads()),
        "rows": [{**r, "ms": round(r["ms"], 3)} for r in rows],
    }, indent=2)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
