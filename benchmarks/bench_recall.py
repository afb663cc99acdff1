"""Recall of the masks on real frames: every detector x canvas/tiling x schedule (issue 11).

Against reference instance masks (``shared/reference/refmasks``: KITTI odometry 06 and
KITTI raw drive 0001; KITTI 03 with references made by ``shared/tools/refmasks.py``),
scored exactly as ``shared/tools/score_masks.py`` does (``dynastereo.eval.refmasks``):

* near-vehicle recall (reference car/truck/bus boxes >= 2000 px matched by an output box
  at IoU >= 0.5), person/bike recall, false boxes per frame (output boxes overlapping no
  reference object: an upper bound, the references miss far cars);
* mask IoU of the ``outline`` and the ``box`` masker on the README's yardstick (inside
  the reference box grown by 10 %, a missed vehicle scoring 0); both maskers mask the SAME
  detections of each frame;
* detection ms (``detect`` + the stage's ``contrast`` and ``carry``) and masking ms
  (disparity, outline, transfer) per stereo pair, mean over the sequence and median.

Every frame of each sequence is processed in order (the schedule and the carried boxes
need the sequence), with the masker ``dynastereo mask`` builds (``build_masker``).

Prints a table per sequence; writes benchmarks/results/recall.json.
Run: DYNASTEREO_DATA=/work/shared/data DYNASTEREO_MODELS=/work/shared/models \\
     .venv/bin/python benchmarks/bench_recall.py [--rows default,frame-every,...] [--ref03 DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from dynastereo.config import Config
from dynastereo.errors import ModelError
from dynastereo.eval.refmasks import load_references, score_frame
from dynastereo.io import open_sequence
from dynastereo.masking import BoxMasker, build_masker
from dynastereo.timing import StageTimer

OUT = Path(__file__).resolve().parent / "results" / "recall.json"
DETECT_STAGES = ("detect", "contrast", "carry")
MASK_STAGES = ("disparity", "outline", "transfer")

#: name -> detector overrides (on top of the defaults of DetectorConfig)
OLD = {"canvas": "model", "contrast": "none", "schedule": "every", "track": False, "score_threshold": 0.25}
ROWS: dict[str, dict] = {
    "shipped-0.1 yolox-nano": {"name": "yolox-nano", **OLD},
    "shipped-0.1 fastestdet": {"name": "fastestdet", **OLD},
    "shipped-0.1 yolov3-tiny": {"name": "yolov3-tiny", **OLD},
    "yolov3-tiny frame": {"name": "yolov3-tiny", **OLD, "canvas": "frame"},
    "fastestdet frame": {"name": "fastestdet", **OLD, "canvas": "frame"},
    "fastestdet frame clahe .15 every+track": {"name": "fastestdet", "canvas": "frame", "schedule": "every",
                                               "score_threshold": 0.15},
    "yolox frame": {"name": "yolox-nano", **OLD, "canvas": "frame"},
    "yolox tiles 3": {"name": "yolox-nano", **OLD, "canvas": "tiles"},
    "yolox frame clahe": {"name": "yolox-nano", **OLD, "canvas": "frame", "contrast": "clahe"},
    "yolox frame clahe .15": {"name": "yolox-nano", **OLD, "canvas": "frame", "contrast": "clahe",
                              "score_threshold": 0.15},
    "yolox frame clahe .15 every+track": {"name": "yolox-nano", "canvas": "frame", "schedule": "every"},
    "yolox frame clahe .15 interval 2+track": {"name": "yolox-nano", "canvas": "frame", "schedule": "interval",
                                               "interval": 2},
    "yolox frame clahe .25 interval 2+track": {"name": "yolox-nano", "canvas": "frame", "schedule": "interval",
                                               "interval": 2, "score_threshold": 0.25},
    "yolox frame clahe .2 interval 2+track": {"name": "yolox-nano", "canvas": "frame", "schedule": "interval",
                                              "interval": 2, "score_threshold": 0.2},
    "yolox frame clahe .15 interval 3+track": {"name": "yolox-nano", "canvas": "frame", "schedule": "interval",
                                               "interval": 3},
    "yolox tiles clahe .15 rotate+track": {"name": "yolox-nano", "canvas": "tiles", "schedule": "rotate"},
    "yolox frame 0.75 clahe .15 every+track": {"name": "yolox-nano", "canvas": "frame", "scale": 0.75,
                                               "schedule": "every"},
    "default .1": {"score_threshold": 0.1},
    "default every": {"schedule": "every"},
    "default": {},
}
QUICK = ["shipped-0.1 yolox-nano", "yolox frame", "yolox frame clahe .15", "default"]


def sequences(data: Path, ref03: Path | None) -> list[tuple[str, Path, Path]]:
    shared = data.parent
    out = [
        ("06", data / "kitti_odometry/dataset/sequences/06", shared / "reference/refmasks/seq06"),
        ("raw0001", data / "kitti_raw/2011_09_26/2011_09_26_drive_0001_sync", shared / "reference/refmasks/raw_0001"),
    ]
    if ref03 is not None:
        out.append(("03", data / "kitti_odometry/dataset/sequences/03", ref03))
    return out


def make_ref03(data: Path, models: Path, out: Path) -> None:
    """References for KITTI 03 with the shared tool (about 1.2 s a frame)."""
    tool = data.parent / "tools/refmasks.py"
    images = sorted((data / "kitti_odometry/dataset/sequences/03/image_0").glob("*.png"))
    print(f"making KITTI 03 references in {out} ({len(images)} frames, ~{1.2 * len(images):.0f} s) ...", flush=True)
    subprocess.run([sys.executable, str(tool), "--model", str(models / "yolov8n-seg-int8/yolov8n-seg_int8.onnx"),
                    "--out", str(out), "--images", *map(str, images)], check=True)


def stats(v: list[float]) -> dict[str, float]:
    a = np.asarray(v, np.float64)
    return {"mean": round(float(a.mean()), 2), "median": round(float(np.median(a)), 2)} if a.size else {}


def run_row(overrides: dict, seq_dir: Path, ref_dir: Path, models: Path, step: int) -> dict:
    cfg = Config().with_overrides({f"detector.{k}": v for k, v in overrides.items()})
    seq = open_sequence(seq_dir)
    outline = build_masker(cfg, seq.calibration, models_dir=models)
    box = BoxMasker(outline.detector, outline.matcher, cfg.masker.outline)
    refs = {r.index: r for r in load_references(ref_dir)}
    timer, btimer = StageTimer(), StageTimer()
    so = sb = None
    detect_ms, mask_ms = [], []
    for i in range(0, len(seq), step):
        frame = seq.frame(i)
        timer.start_frame(i)
        dets = outline.detector.detect_frame(frame, timer)  # the DetectionStage
        m = outline.mask_detections(frame, dets, timer)
        rec = timer.end_frame()["ms"]
        btimer.start_frame(i)
        mb = box.mask_detections(frame, dets, btimer)
        btimer.end_frame()
        detect_ms.append(sum(rec.get(k, 0.0) for k in DETECT_STAGES))
        mask_ms.append(sum(rec.get(k, 0.0) for k in MASK_STAGES))
        if i in refs:
            so = score_frame(refs[i], dets.boxes, m.left, so)
            sb = score_frame(refs[i], dets.boxes, mb.left, sb)
    det = outline.detector.detector
    total = [a + b for a, b in zip(detect_ms, mask_ms)]
    return {
        "detector": cfg.detector.name,
        "settings": overrides,
        "canvas": list(det.canvas_size) if getattr(det, "canvas_size", None) else None,
        "frames": len(detect_ms),
        **so.to_dict(),
        "mask_iou_outline": round(so.mask_iou_vehicles, 4),
        "mask_iou_box": round(sb.mask_iou_vehicles, 4),
        "detect_ms": stats(detect_ms),
        "mask_ms": stats(mask_ms),
        "detect_plus_mask_ms": stats(total),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rows", default="all", help=f"comma-separated row names, 'quick' ({', '.join(QUICK)}) or all")
    ap.add_argument("--step", type=int, default=1, help="every step-th frame (default all; schedules assume 1)")
    ap.add_argument("--ref03", type=Path, default=None, help="KITTI 03 reference folder (made when missing)")
    ap.add_argument("--no-03", action="store_true", help="only 06 and raw 0001")
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args()
    data = Path(os.environ.get("DYNASTEREO_DATA", "")).expanduser()
    models = Path(os.environ.get("DYNASTEREO_MODELS", "")).expanduser()
    if not (data / "kitti_odometry").is_dir() or not models.is_dir():
        sys.exit("set DYNASTEREO_DATA and DYNASTEREO_MODELS (see the docstring)")
    ref03 = None
    if not a.no_03:
        ref03 = a.ref03 or Path.home() / ".cache/dynastereo/refmasks/seq03"
        if not any(ref03.glob("*.json")):
            make_ref03(data, models, ref03)
    names = list(ROWS) if a.rows == "all" else QUICK if a.rows == "quick" else [r.strip() for r in a.rows.split(",")]
    unknown = [n for n in names if n not in ROWS]
    if unknown:
        sys.exit(f"unknown rows {unknown}; known: {', '.join(ROWS)}")
    seqs = sequences(data, ref03)
    results: dict[str, dict] = {}
    for name in names:
        results[name] = {}
        for sname, sdir, rdir in seqs:
            t0 = time.perf_counter()
            try:
                r = run_row(ROWS[name], sdir, rdir, models, a.step)
            except ModelError as e:
                print(f"{name}: skipped ({e})")
                results.pop(name)
                break
            r["wall_s"] = round(time.perf_counter() - t0, 1)
            results[name][sname] = r
            print(f"{name:42s} {sname:8s} veh {r['recall_vehicles']:.2f}  riders {r['recall_riders']:.2f}  "
                  f"false/frame {r['false_boxes_per_frame']:.1f}  IoU outline {r['mask_iou_outline']:.3f} "
                  f"box {r['mask_iou_box']:.3f}  detect {r['detect_ms']['mean']:.1f} / mask {r['mask_ms']['mean']:.1f} "
                  f"ms (mean; median {r['detect_ms']['median']:.1f} / {r['mask_ms']['median']:.1f})", flush=True)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    doc = {"machine": platform.platform(), "cpus": os.cpu_count(), "rows": results,
           "default": Config().detector.__dict__}
    a.out.write_text(json.dumps(doc, indent=1, default=str))
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
