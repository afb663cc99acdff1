"""Recall of the masks on real frames: every detector x canvas/tiling x schedule.

Against reference instance masks (``shared/reference/refmasks``: KITTI odometry 06 and
KITTI raw drive 0001; KITTI 03 with references made by ``shared/tools/refmasks.py``),
scored exactly as ``shared/tools/score_masks.py`` does (``dynastereo.eval.refmasks``):

* near-vehicle recall (reference car/truck/bus boxes >= 2000 px matched by an output box
  at IoU >= 0.5), person/bike recall, false boxes per frame (output boxes overlapping no
  reference object: an upper bound, the references miss far cars);
* mask IoU of the ``outline`` and the ``box`` masker on the yardstick of docs/design/finding-objects.md (inside
  the reference box grown by 10 %, a missed vehicle scoring 0); both maskers mask the SAME
  detections of each frame;
* detection ms (``detect`` + the stage's ``contrast`` and ``carry``) and masking ms
  (disparity, outline, transfer) per stereo pair (CPU), mean over the sequence and median;
* **CPU ms a stereo pair** (the masking cost's yardstick): the process time (all threads) of the
  detection stage plus the outline masker, mean over ALL frames (the detector's runs
  included; the network is made at its canvas -- graph rewrite, compilation -- before
  the first frame, as a long-running process would have it), and the detector's own process time on the frames it runs; the CPU ms of
  every stage (``stage_ms``: process time, mean over all frames; ``detect_ms`` and
  ``mask_ms`` are the same process times summed);
* which runtime ran the network (``detector.runtime`` / ``detector.precision``).

Rows may set any configuration key with a dotted name (``masker.outline.dilate``); plain
names are ``detector.`` keys.  A sequence without references (KITTI 03 without ``--ref03``
references) still gets its CPU figures, with no recall.

Every frame of each sequence is processed in order (the schedule and the carried boxes
need the sequence), with the masker ``dynastereo mask`` builds (``build_masker``).

Prints a table per sequence; writes benchmarks/results/recall.json (the cheap-masking rows:
benchmarks/results/recall_cheap_masking.json and
benchmarks/results/recall_stereo_scale2.json; FastestDet on every frame beside the default:
benchmarks/results/recall_fastestdet.json).
Run: DYNASTEREO_DATA=/work/shared/data DYNASTEREO_MODELS=/work/shared/models \\
     .venv/bin/python benchmarks/bench_recall.py [--rows default,frame-every,...] [--ref03 DIR]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np

from _common import data_dir, data_path, machine, models_dir, results_path, write_json
from dynastereo.config import Config
from dynastereo.errors import ModelError
from dynastereo.eval.refmasks import load_references, score_frame
from dynastereo.io import open_sequence
from dynastereo.masking import BoxMasker, build_masker
from dynastereo.timing import StageTimer

OUT = results_path("recall")
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
    # the runtime and precision of the network (the default schedule otherwise)
    "ort f32 2t": {"runtime": "onnxruntime", "threads": 2},
    "ort f32 1t": {"runtime": "onnxruntime", "threads": 1},
    "ov f32 1t": {"runtime": "openvino", "precision": "f32", "threads": 1},
    "ov bf16 1t": {"runtime": "openvino", "precision": "bf16", "threads": 1},
    "ov bf16 2t": {"runtime": "openvino", "precision": "bf16", "threads": 2},
    # the schedule and the canvas (bf16, 1 thread)
    "ov bf16 1t interval 3": {"runtime": "openvino", "precision": "bf16", "threads": 1, "interval": 3},
    "ov bf16 1t band .25": {"runtime": "openvino", "precision": "bf16", "threads": 1, "band_top": 0.25},
    "ov bf16 1t band .25 interval 3": {"runtime": "openvino", "precision": "bf16", "threads": 1,
                                       "band_top": 0.25, "interval": 3},
    "ort f32 1t band .25": {"runtime": "onnxruntime", "threads": 1, "band_top": 0.25},
    "ov bf16 1t band .25 carry/2": {"runtime": "openvino", "precision": "bf16", "threads": 1, "band_top": 0.25,
                                    "carry_downscale": 2},
    "default carry-outline": {"masker.outline.carry_outline": True},
    "default band .15": {"band_top": 0.15},
    "default no band": {"band_top": 0.0},
    "ov bf16 1t carry/2": {"runtime": "openvino", "precision": "bf16", "threads": 1, "carry_downscale": 2},
    # grey frames as three equal channels (before) or into the one-channel graph (default)
    "default 3 channels": {"grey_input": False},
    "default stereo/2": {"stereo.scale": 2},  # the masks' disparity on half-size images
    # the cheap-masking search (stereo.scale 2 is the default since): the masking before it, explicit
    "previous": {"stereo.scale": 1, "carry_downscale": 1},
    # the cheap-masking search: half-size disparity and carrying first, then the network's canvas and runtime
    "stereo/2 carry/2": {"stereo.scale": 2, "carry_downscale": 2},
    "stereo/2 carry/2 band .25": {"stereo.scale": 2, "carry_downscale": 2, "band_top": 0.25},
    "stereo/2 carry/2 ov bf16": {"stereo.scale": 2, "carry_downscale": 2, "runtime": "openvino",
                                 "precision": "bf16"},
    "stereo/2 carry/2 band .25 ov bf16": {"stereo.scale": 2, "carry_downscale": 2, "band_top": 0.25,
                                          "runtime": "openvino", "precision": "bf16"},
    "stereo/2 carry/2 scale .8": {"stereo.scale": 2, "carry_downscale": 2, "scale": 0.8},
    "stereo/2 carry/2 band .25 ov bf16 interval 3": {"stereo.scale": 2, "carry_downscale": 2, "band_top": 0.25,
                                                     "runtime": "openvino", "precision": "bf16", "interval": 3},
    "ov bf16 1t band .25 carry/2 3 channels": {"runtime": "openvino", "precision": "bf16", "threads": 1,
                                               "band_top": 0.25, "carry_downscale": 2, "grey_input": False},
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


def sequences_cpu03(data: Path) -> list[tuple[str, Path, Path | None]]:
    """KITTI 03 without references: CPU figures only."""
    return [("03", data / "kitti_odometry/dataset/sequences/03", None)]


def make_ref03(data: Path, models: Path, out: Path) -> None:
    """References for KITTI 03 with the shared tool (about 1.2 s a frame)."""
    tool = data.parent / "tools/refmasks.py"
    images = sorted((data / "kitti_odometry/dataset/sequences/03/image_0").glob("*.png"))
    print(f"making KITTI 03 references in {out} ({len(images)} frames, ~{1.2 * len(images):.0f} s) ...", flush=True)
    subprocess.run([sys.executable, str(tool), "--model", str(models / "yolov8n-seg-int8/yolov8n-seg_int8.onnx"),
                    "--out", str(out), "--images", *map(str, images)], check=True)


class CpuStageTimer(StageTimer):
    """A StageTimer whose stages are PROCESS time (all threads), not wall time: on a busy
    two-core machine wall time mostly measures the other processes."""

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        c0 = time.process_time()
        try:
            yield
        finally:
            self.add(name, (time.process_time() - c0) * 1000.0)


def stats(v: list[float]) -> dict[str, float]:
    a = np.asarray(v, np.float64)
    return {"mean": round(float(a.mean()), 2), "median": round(float(np.median(a)), 2)} if a.size else {}


def run_row(overrides: dict, seq_dir: Path, ref_dir: Path | None, models: Path, step: int) -> dict:
    cfg = Config().with_overrides({(k if "." in k else f"detector.{k}"): v for k, v in overrides.items()})
    seq = open_sequence(seq_dir)
    outline = build_masker(cfg, seq.calibration, models_dir=models)
    box = BoxMasker(outline.detector, outline.matcher, cfg.masker.outline)
    refs = {r.index: r for r in load_references(ref_dir)} if ref_dir is not None and ref_dir.is_dir() else {}
    timer, btimer = CpuStageTimer(), StageTimer()
    so = sb = None
    detect_ms, mask_ms, cpu_ms, net_cpu_ms = [], [], [], []
    det0 = outline.detector.detector
    if hasattr(det0, "plan"):  # the network at its canvas is made (compiled) before the clock runs
        det0.plan(*seq.frame(0).left.shape[1::-1])
    for i in range(0, len(seq), step):
        frame = seq.frame(i)
        frame.left_gray, frame.right_gray  # noqa: B018 - the image read is not masking
        timer.start_frame(i)
        c0 = time.process_time()
        dets = outline.detector.detect_frame(frame, timer)  # the DetectionStage
        c1 = time.process_time()
        m = outline.mask_detections(frame, dets, timer)
        cpu_ms.append((time.process_time() - c0) * 1000.0)
        rec = timer.end_frame()["ms"]
        if "detect" in rec:
            net_cpu_ms.append((c1 - c0) * 1000.0)
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
    base = getattr(det, "base", det)
    rt = getattr(base, "runtime", None)
    n = len(timer.frames)
    stage_ms = {k: round(sum(f["ms"].get(k, 0.0) for f in timer.frames) / n, 2)
                for k in timer.stage_names() if k != "total"}
    return {
        "detector": cfg.detector.name,
        "settings": overrides,
        "runtime": rt.label if rt is not None else None,
        "threads": cfg.detector.threads,
        "canvas": list(det.canvas_size) if getattr(det, "canvas_size", None) else None,
        "frames": len(detect_ms),
        **(so.to_dict() if so is not None else {"recall_vehicles": None, "recall_riders": None,
                                                "false_boxes_per_frame": None}),
        "mask_iou_outline": round(so.mask_iou_vehicles, 4) if so is not None else None,
        "mask_iou_box": round(sb.mask_iou_vehicles, 4) if sb is not None else None,
        "detect_ms": stats(detect_ms),
        "mask_ms": stats(mask_ms),
        "detect_plus_mask_ms": stats(total),
        "cpu_ms": stats(cpu_ms),
        "network_cpu_ms": stats(net_cpu_ms),
        "stage_ms": stage_ms,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rows", default="all", help=f"comma-separated row names, 'quick' ({', '.join(QUICK)}) or all")
    ap.add_argument("--step", type=int, default=1, help="every step-th frame (default all; schedules assume 1)")
    ap.add_argument("--ref03", type=Path, default=None, help="KITTI 03 reference folder (made when missing)")
    ap.add_argument("--no-03", action="store_true", help="only 06 and raw 0001")
    ap.add_argument("--cpu-03", action="store_true", help="KITTI 03 for its CPU figures only (no references made)")
    ap.add_argument("--seqs", default="", help="comma-separated subset of 06,raw0001,03")
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args()
    data, models = data_dir(), models_dir()
    data_path("kitti_odometry", data=data)
    ref03 = None
    if not a.no_03 and not a.cpu_03:
        ref03 = a.ref03 or Path.home() / ".cache/dynastereo/refmasks/seq03"
        if not any(ref03.glob("*.json")):
            make_ref03(data, models, ref03)
    names = list(ROWS) if a.rows == "all" else QUICK if a.rows == "quick" else [r.strip() for r in a.rows.split(",")]
    unknown = [n for n in names if n not in ROWS]
    if unknown:
        sys.exit(f"unknown rows {unknown}; known: {', '.join(ROWS)}")
    seqs = sequences(data, ref03)
    if a.cpu_03 and ref03 is None:
        seqs += sequences_cpu03(data)
    if a.seqs:
        seqs = [s for s in seqs if s[0] in a.seqs.split(",")]
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
            def f(v: float | None, fmt: str = ".2f") -> str:
                return "  -  " if v is None else format(v, fmt)

            print(f"{name:42s} {sname:8s} veh {f(r['recall_vehicles'])}  riders {f(r['recall_riders'])}  "
                  f"false/frame {f(r['false_boxes_per_frame'], '.1f')}  IoU outline {f(r['mask_iou_outline'], '.3f')} "
                  f"box {f(r['mask_iou_box'], '.3f')}  CPU {r['cpu_ms']['mean']:.1f} ms/pair "
                  f"(network {r['network_cpu_ms'].get('mean', 0):.1f} on its frames)  CPU detect "
                  f"{r['detect_ms']['mean']:.1f} / mask {r['mask_ms']['mean']:.1f}  [{r['runtime']}]", flush=True)
            print("    stages (CPU ms, mean over all frames): "
                  + "  ".join(f"{k} {v:.1f}" for k, v in r["stage_ms"].items()), flush=True)
    doc = {"machine": machine(), "rows": results, "default": Config().detector.__dict__}
    write_json(a.out, doc, default=str)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
