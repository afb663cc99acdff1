"""Benchmark masking on KITTI odometry seq 06 and 03 (thesis 4.4.1: 49-71 ms per image).

Per stereo pair the detector (yolox-nano; yolov3-tiny if it is missing) runs once on the
left image; every disparity-based masker then masks the SAME detections, so the numbers
compare the masking alone:

1. ``mask`` ms = disparity + outline + transfer for BOTH images, detector excluded
   (median / p90 over frames; each frame's value is the median of ``--repeats`` runs),
   for the outline masker with disparity in the boxes' band only (full and half
   resolution) and over the full frame, and for the box masker; StereoBM,
   numDisparities 96 (the default config).  Target: median <= 15 ms.
2. Quality against the seg masker's pixel masks (YOLOv8n-seg on both images, the
   stand-in for DynaSLAM's Mask R-CNN): objects matched by box IoU >= 0.5, then per
   object mask IoU, precision (masked pixels inside the seg mask) and recall (seg pixels
   masked), left and right images.  The right seg instance is the one matched to the left
   instance across the pair.
3. Time of each masker per stereo pair, detector/network included; for the outline
   maskers, how often the road line (ground removal) was fitted reliably.
4. Synthetic streets with exact ground truth (``dynastereo synth``: crossing, convoy,
   mixed; 40 frames at 640x192, generated into a temporary folder): the ORACLE boxes
   (no detector), outline vs box, per-object IoU / precision / recall against the GT
   instance masks, left and right images, objects nearer than 30 m
   (``dynastereo.eval.masks.score_frame``) -- with the default stereo (BM 15), with
   two denser matchers (BM 9 + WLS, SGBM 3-way 5) and with the scenes' exact disparity
   (the ceiling of the outline algorithm); and, for BM 15 and the exact disparity, where
   the outline's pixels go wrong (``LossBudget``: its own false positives -- those at the
   box's base, the road -- other boxes' false positives, missed pixels, box fallbacks).

Prints tables; writes benchmarks/results/mask.json.
Run: DYNASTEREO_DATA=/work/shared/data DYNASTEREO_MODELS=/work/shared/models \\
     .venv/bin/python benchmarks/bench_mask.py [--step 2] [--repeats 3] [--synth-frames 40 | --no-synth] [--no-kitti]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from _common import data_dir, machine, models_dir, results_path, stats, write_json
from dynastereo.config import DetectorConfig, OutlineConfig, StereoConfig
from dynastereo.errors import ModelError
from dynastereo.io import open_sequence
from dynastereo.masking import BoxMasker, OutlineMasker, SegMasker, StereoMatcher
from dynastereo.masking.detection import create_detector, create_seg_model
from dynastereo.masking.boxes import box_iou
from dynastereo.timing import StageTimer
from dynastereo.datatypes import Detections

OUT = results_path("mask")
MASK_STAGES = ("disparity", "outline", "transfer", "segment", "boxes")
TARGET_MS = 15.0


class Fixed:
    """A 'detector' handing back detections computed beforehand (timed separately)."""

    name = "fixed"
    class_names: tuple[str, ...] = ()

    def detect(self, image):  # pragma: no cover - not used (mask_labels gets detections)
        raise RuntimeError


def run_timed(fn, repeats: int) -> tuple[dict[str, float], object]:
    """Per-stage ms (median over repeats) of ``fn(timer)`` and its last result."""
    recs = []
    out = None
    for _ in range(repeats):
        t = StageTimer()
        t.add_derived("mask", MASK_STAGES)
        t.start_frame(0)
        out = fn(t)
        recs.append(t.end_frame()["ms"])
    keys = set().union(*recs)
    return {k: float(np.median([r.get(k, 0.0) for r in recs])) for k in keys}, out


def match_boxes(a: np.ndarray, b: np.ndarray, thr: float = 0.5) -> list[tuple[int, int]]:
    if len(a) == 0 or len(b) == 0:
        return []
    iou = box_iou(a, b)
    pairs = []
    while True:
        i, j = np.unravel_index(int(np.argmax(iou)), iou.shape)
        if iou[i, j] < thr:
            return pairs
        pairs.append((int(i), int(j)))
        iou[i, :] = -1
        iou[:, j] = -1


def quality(pred: np.ndarray, ref: np.ndarray) -> tuple[float, float, float]:
    inter = float(np.count_nonzero(pred & ref))
    union = float(np.count_nonzero(pred | ref))
    return inter / max(union, 1.0), inter / max(np.count_nonzero(pred), 1), inter / max(np.count_nonzero(ref), 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--step", type=int, default=1, help="use every STEP-th frame")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2, help="detector threads")
    ap.add_argument("--no-seg", action="store_true", help="skip the seg baseline (no quality numbers)")
    ap.add_argument("--synth-frames", type=int, default=40, help="frames per synthetic scenario")
    ap.add_argument("--no-synth", action="store_true", help="skip the synthetic ground-truth section")
    ap.add_argument("--no-kitti", action="store_true", help="skip the KITTI section")
    args = ap.parse_args()
    synth_res = None if args.no_synth else synth_section(args.synth_frames)
    if args.no_kitti:  # keep the KITTI section of an earlier run
        old = json.loads(OUT.read_text()) if OUT.exists() else {"benchmark": "mask"}
        _write({**old, "synth": synth_res})
        return
    data, models = data_dir(), models_dir()

    det_name = "yolox-nano"
    try:
        detector = create_detector(DetectorConfig(name=det_name, threads=args.threads), models)
    except ModelError as e:
        print(f"yolox-nano unavailable ({e}); falling back to yolov3-tiny")
        det_name = "yolov3-tiny"
        detector = create_detector(DetectorConfig(name=det_name, threads=args.threads), models)
    seg = None if args.no_seg else SegMasker(
        create_seg_model("yolov8n-seg-int8", DetectorConfig(threads=args.threads), models), max_disparity=96)

    base = StereoConfig()  # BM, numDisparities 96, block 15
    ocfg = OutlineConfig()
    configs = {
        "outline band 1/1": OutlineMasker(Fixed(), StereoMatcher(base), ocfg),
        "outline band 1/2": OutlineMasker(Fixed(), StereoMatcher(replace(base, scale=2)), ocfg),
        "outline full 1/1": OutlineMasker(Fixed(), StereoMatcher(replace(base, region="full")), ocfg),
        "outline band 1/2 sgbm3way": OutlineMasker(
            Fixed(), StereoMatcher(replace(base, algorithm="sgbm3way", block_size=5, scale=2)), ocfg),
        "box band 1/1": BoxMasker(Fixed(), StereoMatcher(base), ocfg),
    }
    per_frame: dict[str, list[dict]] = {k: [] for k in configs}
    ground_ok: dict[str, list[bool]] = {k: [] for k in configs if isinstance(configs[k], OutlineMasker)}
    detect_ms: list[float] = []
    seg_ms: list[dict[str, float]] = []
    qual: dict[str, dict[str, list[tuple[float, float, float]]]] = {
        k: {"left": [], "right": []} for k in configs
    }
    n_frames = n_objects = 0
    t_start = time.perf_counter()
    for seq_name in ("06", "03"):
        seq = open_sequence(data / "kitti_odometry/dataset/sequences" / seq_name)
        for idx in range(0, len(seq), args.step):
            frame = seq.frame(idx)
            n_frames += 1
            d_ms, dets = run_timed(lambda t: _detect(detector, frame, t), args.repeats)
            detect_ms.append(d_ms.get("detect", 0.0))
            n_objects += len(dets)
            ref = None
            if seg is not None:
                s_ms, ref = run_timed(lambda t: seg.segment_both(frame, t), 1)
                seg_ms.append(s_ms)
            for name, masker in configs.items():
                ms, (masks, lab_l, lab_r) = run_timed(lambda t: masker.mask_labels(frame, dets, t), args.repeats)
                ms["n_det"] = len(dets)
                per_frame[name].append(ms)
                if name in ground_ok and len(dets):
                    ground_ok[name].append(bool(masks.ground is not None and masks.ground.ok))
                if ref is None:
                    continue
                _, sl, sr, match = ref
                for i, k in match_boxes(sl.boxes, dets.boxes):
                    qual[name]["left"].append(quality(lab_l == k + 1, sl.masks[i]))
                    j = int(match[i])
                    if j >= 0:
                        qual[name]["right"].append(quality(lab_r == k + 1, sr.masks[j]))
            print(f"\r{seq_name}/{idx:06d}: {len(dets)} detections", end="", flush=True)
    print(f"\n{n_frames} stereo pairs, {n_objects} detections, {time.perf_counter() - t_start:.0f} s")

    det_stats = stats(detect_ms)
    results: dict[str, dict] = {}
    print("\n`mask` = disparity + outline + transfer, both images, detector excluded (ms per stereo pair)")
    print("| masker | mask median | mask p90 | median, frames with detections | disparity | outline/boxes | transfer | per pair incl. detect |")
    print("|---|---|---|---|---|---|---|---|")
    for name, recs in per_frame.items():
        mask = [r.get("mask", 0.0) for r in recs]
        with_det = [r.get("mask", 0.0) for r in recs if r["n_det"] > 0]
        total = [r.get("mask", 0.0) + d for r, d in zip(recs, detect_ms)]
        res = {
            "mask": stats(mask),
            "mask_frames_with_detections": stats(with_det),
            "disparity": stats(r.get("disparity", 0.0) for r in recs),
            "outline": stats(r.get("outline", 0.0) + r.get("boxes", 0.0) for r in recs),
            "transfer": stats(r.get("transfer", 0.0) for r in recs),
            "per_pair_with_detect": stats(total),
        }
        if name in ground_ok:
            res["road_line_ok_fraction"] = round(float(np.mean(ground_ok[name])), 3) if ground_ok[name] else None
        for side in ("left", "right"):
            q = np.asarray(qual[name][side], np.float64).reshape(-1, 3)
            res[f"vs_seg_{side}"] = {
                "objects": int(len(q)),
                "iou": round(float(q[:, 0].mean()), 4) if len(q) else None,
                "precision": round(float(q[:, 1].mean()), 4) if len(q) else None,
                "recall": round(float(q[:, 2].mean()), 4) if len(q) else None,
            }
        results[name] = res
        print(f"| {name} | {res['mask']['median']:.2f} | {res['mask']['p90']:.2f} | "
              f"{res['mask_frames_with_detections']['median']:.2f} | {res['disparity']['median']:.2f} | "
              f"{res['outline']['median']:.2f} | {res['transfer']['median']:.2f} | "
              f"{res['per_pair_with_detect']['median']:.2f} |")
    seg_res = None
    if seg_ms:
        seg_res = {k: stats(r.get(k, 0.0) for r in seg_ms) for k in ("detect", "segment", "mask")}
        seg_res["per_pair"] = stats(r.get("detect", 0.0) + r.get("segment", 0.0) for r in seg_ms)
        print(f"| seg (yolov8n-seg, both images) | {seg_res['mask']['median']:.2f} | {seg_res['mask']['p90']:.2f} | "
              f"- | - | - | - | {seg_res['per_pair']['median']:.2f} |")
    print(f"| none | 0 | 0 | - | - | - | - | 0 |")
    print(f"\ndetector {det_name} on the left image: median {det_stats['median']:.2f} ms, p90 {det_stats['p90']:.2f} ms")
    best = results["outline band 1/1"]["mask"]["median"]
    print(f"target `mask` median <= {TARGET_MS} ms (default config, outline band 1/1): "
          f"{best:.2f} ms -> {'MET' if best <= TARGET_MS else 'MISSED'}")

    if seg_ms:
        print("\nper-object agreement with the seg masks (mean over matched objects)")
        print("| masker | objects L | IoU L | precision L | recall L | objects R | IoU R | precision R | recall R |")
        print("|---|---|---|---|---|---|---|---|---|")
        for name, res in results.items():
            l, r = res["vs_seg_left"], res["vs_seg_right"]
            fmt = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
            print(f"| {name} | {l['objects']} | {fmt(l['iou'])} | {fmt(l['precision'])} | {fmt(l['recall'])} | "
                  f"{r['objects']} | {fmt(r['iou'])} | {fmt(r['precision'])} | {fmt(r['recall'])} |")

    print("\nroad line fitted reliably (frames with detections): " + ", ".join(
        f"{k} {v['road_line_ok_fraction']}" for k, v in results.items() if "road_line_ok_fraction" in v))
    result = {
        "benchmark": "mask",
        "sequences": ["kitti 06", "kitti 03"],
        "frames": n_frames,
        "step": args.step,
        "repeats": args.repeats,
        "detections": n_objects,
        "detector": {"name": det_name, "ms": det_stats},
        "stereo": "StereoBM numDisparities 96 blockSize 15 (default config) unless named",
        "target_mask_median_ms": TARGET_MS,
        "maskers": results,
        "seg": seg_res,
        "synth": synth_res,
    }
    _write(result)


def _write(result: dict) -> None:
    result["machine"] = machine()
    write_json(OUT, result)
    print(f"\nwrote {OUT}")


SYNTH_SCENARIOS = ("crossing", "convoy", "mixed")
SYNTH_STEREO = {
    "bm 15 (default)": {},
    "bm 9 + wls": {"stereo.block_size": 9, "stereo.wls": True},
    "sgbm3way 5": {"stereo.algorithm": "sgbm3way", "stereo.block_size": 5},
    "exact (GT) disparity": {},  # the ceiling: the synthetic scene's exact disparity
}
EXACT = "exact (GT) disparity"
# the matchers whose outline errors are broken down (the default and the exact disparity)
BUDGET_STEREO = ("bm 15 (default)", EXACT)


def synth_section(frames: int) -> dict:
    """Outline vs box on synthetic streets with exact GT (oracle boxes)."""
    import tempfile

    from dynastereo.api import load_sequence
    from dynastereo.masking import build_masker
    from dynastereo.config import Config
    from dynastereo.eval.masks import LossBudget, MaskAgreement, score_frame
    from dynastereo.synth import OracleDetector, generate, read_gt_disparity, read_gt_masks, read_objects

    out: dict[str, dict] = {}
    budgets: dict[str, dict] = {}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="dynastereo-synth-") as tmp:
        for scn in SYNTH_SCENARIOS:
            path = generate(Path(tmp) / scn, scn, frames=frames)
            seq, gt = load_sequence(path), read_objects(path)
            oracle = OracleDetector(path)  # the same boxes the maskers' oracle detector returns
            for st_name, st in SYNTH_STEREO.items():
                for kind in ("outline", "box"):
                    if kind == "box" and (st or st_name == EXACT):
                        continue  # the boxes do not depend on the matcher (but for the right shift)
                    cfg = Config().with_overrides({"detector.name": "oracle", "masker.kind": kind, **st})
                    masker = build_masker(cfg, seq.calibration, ground_truth=path)
                    if st_name == EXACT:  # the masker's disparity replaced by the exact one
                        masker._disparity = lambda frame, *a, _p=path, **k: read_gt_disparity(_p, frame.index)
                    agg = MaskAgreement()
                    budget = LossBudget() if kind == "outline" and st_name in BUDGET_STEREO else None
                    for i in range(len(seq)):
                        dets = oracle.detect_frame(i)
                        m, left_labels, _ = masker.mask_labels(seq.frame(i), dets)
                        gl, gr = read_gt_masks(path, i)
                        agg.scores += score_frame(i, {"left": m.left, "right": m.right}, {"left": gl, "right": gr},
                                                  gt.frames[i])
                        if budget is not None:
                            budget.add(gt.frames[i], oracle.objects(i), m.objects, left_labels, gl)
                    r = {f"{k}_{v}": round(agg.mean(v, k), 4) for k in ("iou", "precision", "recall")
                         for v in ("left", "right")}
                    r.update(agg.summary())
                    if budget is not None:
                        budgets[f"{scn} | {st_name}"] = budget.summary()
                    out[f"{scn} | {kind} | {st_name}" if kind == "outline" else f"{scn} | box"] = r
            print(f"synth {scn}: done ({time.perf_counter() - t0:.0f} s)", flush=True)
    print(f"\nsynthetic streets, {frames} frames each, 640x192, oracle boxes: per-object mean vs GT instance masks "
          "(objects < 30 m); L / R = left / right image")
    print("| scenario | masker | stereo | IoU L | IoU R | IoU | precision L | precision R | recall L | recall R | objects L/R |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for key, r in out.items():
        parts = key.split(" | ")
        scn, kind = parts[0], parts[1]
        st_name = parts[2] if len(parts) > 2 else "bm 15 (default)"
        print(f"| {scn} | {kind} | {st_name} | {r['iou_left']:.3f} | {r['iou_right']:.3f} | {r['iou']:.3f} | "
              f"{r['precision_left']:.3f} | {r['precision_right']:.3f} | {r['recall_left']:.3f} | "
              f"{r['recall_right']:.3f} | {r['objects_left']}/{r['objects_right']} |")
    print("\nwhere the outline's left-image pixels go wrong (pixels inside the objects' GT boxes, objects < 30 m; "
          "share of the object pixels; 'road at base' = false positives in the bottom quarter of the box)")
    print("| scenario | stereo | objects outlined | box fallbacks | false pos. own | of which road at base | "
          "false pos. other boxes | missed |")
    print("|---|---|---|---|---|---|---|---|")
    for key, b in budgets.items():
        scn, st_name = key.split(" | ")
        print(f"| {scn} | {st_name} | {b['outlined']} | {b['fallbacks']} | {b['fp_own']:.3f} | {b['fp_own_base']:.3f} | "
              f"{b['fp_other']:.3f} | {b['missed']:.3f} |")
    return {"frames": frames, "size": "640x192", "detector": "oracle (GT boxes)", "results": out,
            "loss_budget": budgets}


def _detect(detector, frame, timer: StageTimer) -> Detections:
    with timer.stage("detect"):
        return detector.detect(frame.left)


if __name__ == "__main__":
    main()
