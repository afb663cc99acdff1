"""Benchmark SLAM + masking on the synthetic dynamic scenes (exact ground truth).

For every scenario (default static, crossing, convoy, oncoming, mixed; ``loop`` on
request, it is long) and seed, ``dynastereo.synth.generate`` renders ``--frames`` frames
at ``--size`` (cached, see ``--cache``), then ``dynastereo.api.run_sequence`` runs the
whole pipeline (masking on the prefetch thread, stereo SLAM with local BA) with

* masker ``none`` (unmasked SLAM);
* maskers ``box`` and ``outline`` on the ground-truth **oracle** boxes;
* masker ``gt``: the ground-truth instance masks of the oracle's objects in both images
  (perfect masks: what the SLAM reaches when masking is not the limit);
* maskers ``box`` and ``outline`` on the real detectors (``yolox-nano``, ``yolov3-tiny``,
  ``fastestdet`` from ``$DYNASTEREO_MODELS``) where they fire on these images: each
  detector's recall is measured first and a detector with recall < ``--min-recall`` on
  a scenario gets no SLAM runs there (reported as "does not fire").  Real detectors run
  on the seeds of ``--detector-seeds`` only (default: the first seed) to bound the time.

Reported per scenario x detector x masker (median over seeds, [min, max] for ATE):

* ``ATE``    APE RMSE (m) after SE(3) alignment, ``dynastereo.eval.evaluate_files``;
* ``drift``  start-anchored final position error, % of the path length;
* ``IoU L/R`` mask IoU against the GT instance masks (objects nearer than 30 m, at least
  50 visible pixels; ``eval.masks.score_mask_dir``) in the left / right image;
* ``recall`` detector recall vs the GT boxes: fraction of GT objects nearer than 30 m
  (>= 50 left pixels) matched one-to-one, class-agnostic, by a detection with IoU >= 0.5
  (oracle: 1 by construction);
* ``FPS``    end-to-end frames per second of the run (masking + SLAM; the machine is
  shared and noisy: indicative only); ``lost`` frames.

And the targets of the synthetic-scenes issue, on the oracle boxes:

* ``convoy`` / ``crossing``: ATE(outline) <= ATE(none) / 3, and ATE(outline) <= 1.5 x the
  ATE on ``static`` (checked against static with the same masker and with none);
* mask IoU(outline) >= IoU(box) + 0.10 (mean of left and right).

Prints tables; writes benchmarks/results/synth_slam.json (every run, the medians, the
targets).  Run:

    DYNASTEREO_MODELS=/work/shared/models .venv/bin/python benchmarks/bench_synth_slam.py \\
        [--seeds 0,1,2] [--frames 120] [--scenarios static,convoy] [--detectors none] [--quick]
"""

from __future__ import annotations

import argparse
import logging
import shutil
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from _common import machine, median, models_dir, results_path, write_json
from _shared_runs import generator_version, sequence
from dynastereo.api import run_sequence
from dynastereo.config import Config, DetectorConfig
from dynastereo.errors import ModelError
from dynastereo.eval import evaluate_files
from dynastereo.eval.masks import score_mask_dir
from dynastereo.synth import OracleDetector, read_gt_masks, read_objects
from dynastereo.datatypes import StereoMasks

OUT = results_path("synth_slam")
SCENARIOS = ("static", "crossing", "convoy", "oncoming", "mixed")
REAL_DETECTORS = ("yolox-nano", "yolov3-tiny", "fastestdet")
MAX_DISTANCE = 30.0
MIN_PIXELS = 50
TARGET_RATIO_NONE = 1.0 / 3.0
TARGET_RATIO_STATIC = 1.5
TARGET_IOU_GAIN = 0.10


# ------------------------------------------------------------------------------ sequences


# ------------------------------------------------------------------------------ recall


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU matrix of boxes x1y1x2y2 (N, 4) x (M, 4)."""
    x1 = np.maximum(a[:, None, 0], b[None, :, 0])
    y1 = np.maximum(a[:, None, 1], b[None, :, 1])
    x2 = np.minimum(a[:, None, 2], b[None, :, 2])
    y2 = np.minimum(a[:, None, 3], b[None, :, 3])
    inter = np.clip(x2 - x1, 0, None) * np.clip(y2 - y1, 0, None)
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    return inter / np.maximum(area_a[:, None] + area_b[None, :] - inter, 1e-9)


def match_gt(iou: np.ndarray, thr: float = 0.5) -> np.ndarray:
    """Which GT rows are matched one-to-one (greedy by IoU) by a detection column with IoU >= thr."""
    m = iou.copy()
    got = np.zeros(m.shape[0], bool)
    while m.size:  # at most min(N, M) rounds: a handful of boxes
        k = int(np.argmax(m))
        i, j = divmod(k, m.shape[1])
        if m[i, j] < thr:
            break
        got[i] = True
        m[i, :] = -1.0
        m[:, j] = -1.0
    return got


def detector_recall(detector, seq: Path) -> dict:
    """Recall of ``detector`` (left images) against the GT boxes of objects < 30 m."""
    gt = read_objects(seq)
    hit = total = 0
    per_label: dict[str, list[int]] = {}
    ms = []
    for i in range(len(gt)):
        objs = [o for o in gt.frame(i) if o.box_left is not None and o.distance < MAX_DISTANCE and o.pixels_left >= MIN_PIXELS]
        img = cv2.imread(str(seq / "image_0" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
        t0 = time.perf_counter()
        det = detector.detect(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
        ms.append((time.perf_counter() - t0) * 1000.0)
        if not objs:
            continue
        g = np.array([o.box_left for o in objs], np.float64)
        boxes = np.asarray(det.boxes, np.float64).reshape(-1, 4)
        got = match_gt(box_iou(g, boxes) if len(boxes) else np.zeros((len(objs), 0)))
        for o, ok in zip(objs, got):
            c = per_label.setdefault(o.label, [0, 0])
            c[0] += int(ok)
            c[1] += 1
        hit += int(got.sum())
        total += len(objs)
    return {
        "recall": round(hit / total, 4) if total else None,
        "matched": hit,
        "objects": total,
        "per_label": {k: {"matched": a, "objects": b, "recall": round(a / b, 4)} for k, (a, b) in sorted(per_label.items())},
        "detect_ms_median": round(float(np.median(ms)), 2) if ms else None,
    }


# ------------------------------------------------------------------------------ one run


class GTMasker:
    """Perfect masks: the GT instance masks (both images) of the objects the oracle
    detector reports (the dynamic classes, moving or parked)."""

    name = "gt"

    def __init__(self, seq: Path):
        self.seq = seq
        self.oracle = OracleDetector(seq)

    def mask(self, frame, timer=None) -> StereoMasks:
        ids = [o.id for o in self.oracle.objects(frame.index)]
        gl, gr = read_gt_masks(self.seq, frame.index)
        return StereoMasks(np.isin(gl, ids).astype(np.uint8) * 255, np.isin(gr, ids).astype(np.uint8) * 255)


def slam_run(seq: Path, work: Path, detector: str, masker: str, seed: int, models_dir: Path | None) -> dict:
    run_dir = work / f"run_{detector}_{masker}"
    shutil.rmtree(run_dir, ignore_errors=True)
    if masker == "gt":
        from dynastereo.runtime import JobKind, JobSpec, OutputSpec, SourceSpec, run

        cfg = Config().with_overrides({"masker.kind": "none", "seed": seed, "motion.mode": "all"})
        res = run(JobSpec(JobKind.RUN, SourceSpec(path=seq), OutputSpec(run_dir), cfg), masker=GTMasker(seq))
    else:
        cfg = Config().with_overrides({"detector.name": detector, "masker.kind": masker, "seed": seed})
        res = run_sequence(seq, run_dir, cfg, models_dir=models_dir, save_masks=masker != "none", overwrite=True)
    ev = evaluate_files(run_dir / "trajectory.kitti.txt", seq.parent.parent / "poses" / "00.txt")
    rec = {
        "ate_rmse": round(float(ev.ape["rmse"]), 4),
        "drift_percent": round(float(ev.drift_percent or 0.0), 3),
        "fps": round(float(res.fps), 2),
        "lost": len(res.lost),
        "iou_left": None,
        "iou_right": None,
    }
    if masker not in ("none", "gt"):
        agree = score_mask_dir(run_dir, seq, max_distance=MAX_DISTANCE).summary()
        rec.update(iou_left=agree["iou_left"], iou_right=agree["iou_right"], mask_precision=agree["precision"],
                   mask_recall=agree["recall"], scored_objects=agree["objects_left"] + agree["objects_right"])
    shutil.rmtree(run_dir, ignore_errors=True)
    return rec


# ------------------------------------------------------------------------------ summary


def _med(v: list) -> float | None:
    return median(v, digits=4, finite=True)


def summarize(runs: list[dict]) -> dict:
    """scenario -> "detector/masker" -> medians over seeds."""
    out: dict[str, dict] = {}
    keys = sorted({(r["scenario"], r["detector"], r["masker"]) for r in runs if "ate_rmse" in r})
    for sc, det, m in keys:
        rs = [r for r in runs if (r["scenario"], r["detector"], r["masker"]) == (sc, det, m) and "ate_rmse" in r]
        ate = [r["ate_rmse"] for r in rs]
        out.setdefault(sc, {})[f"{det}/{m}"] = {
            "detector": det,
            "masker": m,
            "seeds": [r["seed"] for r in rs],
            "ate_rmse": _med(ate),
            "ate_min": round(min(ate), 4),
            "ate_max": round(max(ate), 4),
            "drift_percent": _med([r["drift_percent"] for r in rs]),
            "iou_left": _med([r["iou_left"] for r in rs]),
            "iou_right": _med([r["iou_right"] for r in rs]),
            "recall": _med([r.get("recall") for r in rs]),
            "fps": _med([r["fps"] for r in rs]),
            "lost": int(sum(r["lost"] for r in rs)),
        }
    return out


def targets(runs: list[dict], summary: dict) -> dict:
    """The issue's targets on the oracle boxes, per seed and on the medians."""
    def ate(sc: str, det: str, m: str, seed: int | None = None):
        if seed is None:
            return summary.get(sc, {}).get(f"{det}/{m}", {}).get("ate_rmse")
        v = [r["ate_rmse"] for r in runs if (r["scenario"], r["detector"], r["masker"], r["seed"]) == (sc, det, m, seed) and "ate_rmse" in r]
        return v[0] if v else None

    def iou(sc: str, m: str, seed: int | None = None):
        rows = [r for r in runs if (r["scenario"], r["detector"], r["masker"]) == (sc, "oracle", m) and r.get("iou_left") is not None
                and (seed is None or r["seed"] == seed)]
        if not rows:
            return None
        return float(np.median([(r["iou_left"] + r["iou_right"]) / 2 for r in rows]))

    out: dict[str, dict] = {}
    seeds = sorted({r["seed"] for r in runs})
    for sc in sorted({r["scenario"] for r in runs}):
        t: dict = {}
        if sc in ("convoy", "crossing"):
            for key, seed in [("median", None)] + [(f"seed{s}", s) for s in seeds]:
                a_o, a_n = ate(sc, "oracle", "outline", seed), ate(sc, "none", "none", seed)
                s_o, s_n = ate("static", "oracle", "outline", seed), ate("static", "none", "none", seed)
                row = {"ate_outline": a_o, "ate_none": a_n, "static_outline": s_o, "static_none": s_n}
                if a_o is not None and a_n:
                    row["outline_over_none"] = round(a_o / a_n, 4)
                    row["ok_vs_none"] = bool(a_o <= TARGET_RATIO_NONE * a_n)
                if a_o is not None and s_o:
                    row["outline_over_static_outline"] = round(a_o / s_o, 3)
                    row["ok_vs_static_outline"] = bool(a_o <= TARGET_RATIO_STATIC * s_o)
                if a_o is not None and s_n:
                    row["outline_over_static_none"] = round(a_o / s_n, 3)
                    row["ok_vs_static_none"] = bool(a_o <= TARGET_RATIO_STATIC * s_n)
                a_g, s_g = ate(sc, "gt", "gt", seed), ate("static", "gt", "gt", seed)
                if a_g is not None and s_g:  # the same ratio with perfect masks: the scene's own
                    row.update(ate_gt=a_g, static_gt=s_g, gt_over_static_gt=round(a_g / s_g, 3))
                t[key] = row
        i_o, i_b = iou(sc, "outline"), iou(sc, "box")
        if i_o is not None and i_b is not None:
            t["iou"] = {"outline": round(i_o, 4), "box": round(i_b, 4), "gain": round(i_o - i_b, 4),
                        "ok": bool(i_o >= i_b + TARGET_IOU_GAIN)}
        out[sc] = t
    return out


def fmt(v, spec: str = ".3f") -> str:
    return "-" if v is None else format(v, spec)


def print_tables(summary: dict, tgt: dict, recalls: dict, frames: int, size) -> None:
    for sc, rows in summary.items():
        print(f"\n== {sc}  ({frames} frames, {size[0]}x{size[1]}; ATE median [min, max] over seeds)")
        print(f"{'detector':12s} {'masker':8s} {'ATE m':>7s} {'[min, max]':>17s} {'drift%':>7s} {'IoU L':>6s} {'IoU R':>6s} "
              f"{'recall':>6s} {'FPS':>6s} {'lost':>4s} seeds")
        for key in sorted(rows, key=lambda k: (rows[k]["detector"] != "none", rows[k]["detector"] != "oracle", k)):
            r = rows[key]
            print(f"{r['detector']:12s} {r['masker']:8s} {fmt(r['ate_rmse']):>7s} {'[' + fmt(r['ate_min']) + ', ' + fmt(r['ate_max']) + ']':>17s} "
                  f"{fmt(r['drift_percent'], '.2f'):>7s} {fmt(r['iou_left']):>6s} {fmt(r['iou_right']):>6s} "
                  f"{fmt(r['recall'], '.2f'):>6s} {fmt(r['fps'], '.1f'):>6s} {r['lost']:>4d} {r['seeds']}")
        for det, rec in sorted(recalls.get(sc, {}).items()):
            if not rec.get("fires", True):
                print(f"{det:12s} does not fire here: recall {fmt(rec.get('recall'), '.2f')} (seed {rec['seed']}); no SLAM runs")
    print("\n== targets (oracle boxes)")
    for sc, t in tgt.items():
        for key, row in t.items():
            if key == "iou":
                print(f"{sc:9s} IoU outline {row['outline']:.3f} vs box {row['box']:.3f}: gain {row['gain']:+.3f} "
                      f"(target >= +{TARGET_IOU_GAIN:.2f}) {'OK' if row['ok'] else 'MISSED'}")
            elif "outline_over_none" in row:
                print(f"{sc:9s} {key:7s} ATE outline {fmt(row['ate_outline'])} / none {fmt(row['ate_none'])} = {row['outline_over_none']:.3f} "
                      f"(<= 0.333 {'OK' if row['ok_vs_none'] else 'MISSED'}); / static outline {fmt(row.get('outline_over_static_outline'), '.2f')} "
                      f"({'OK' if row.get('ok_vs_static_outline') else 'MISSED'}), / static none {fmt(row.get('outline_over_static_none'), '.2f')} "
                      f"({'OK' if row.get('ok_vs_static_none') else 'MISSED'}) (<= 1.5)"
                      + (f"; GT masks: {fmt(row['ate_gt'])} / static {fmt(row['static_gt'])} = {row['gt_over_static_gt']:.2f}"
                         if "gt_over_static_gt" in row else ""))


# ------------------------------------------------------------------------------ main


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenarios", default=",".join(SCENARIOS), help="comma list; 'loop' is accepted (long)")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--size", default="640x192")
    ap.add_argument("--maskers", default="none,box,outline,gt", help="none, box, outline, gt (GT masks)")
    ap.add_argument("--detectors", default=",".join(REAL_DETECTORS), help="real detectors, or 'none'")
    ap.add_argument("--detector-seeds", default=None, help="seeds for the real detectors (default: the first seed)")
    ap.add_argument("--min-recall", type=float, default=0.05, help="below this a detector 'does not fire' on a scenario")
    ap.add_argument("--cache", default=None, help="generated sequences (default: $TMPDIR/dynastereo-bench-synth)")
    ap.add_argument("--quick", action="store_true", help="1 seed, 60 frames, oracle boxes only")
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args()
    if args.quick:
        args.seeds, args.frames, args.detectors = "0", 60, "none"
    logging.getLogger("dynastereo").setLevel(logging.ERROR)  # lost frames are counted, not logged
    scenarios = [s for s in args.scenarios.split(",") if s]
    seeds = [int(s) for s in args.seeds.split(",") if s != ""]
    det_seeds = [int(s) for s in args.detector_seeds.split(",")] if args.detector_seeds else seeds[:1]
    w, h = (int(v) for v in args.size.lower().split("x"))
    size = (w, h)
    maskers = [m for m in args.maskers.split(",") if m]
    cache = Path(args.cache) if args.cache else Path(tempfile.gettempdir()) / "dynastereo-bench-synth"
    cache.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="bench_synth_slam_"))

    models = models_dir(required=False)
    detectors: dict[str, object] = {}
    notes = []
    for name in [d for d in args.detectors.split(",") if d and d != "none"]:
        if models is None:
            notes.append(f"{name}: skipped, DYNASTEREO_MODELS is not set")
            continue
        try:
            from dynastereo.masking.detection import create_detector

            detectors[name] = create_detector(DetectorConfig(name=name), models)
        except ModelError as e:
            notes.append(f"{name}: skipped, {e}")
    for n in notes:
        print(n)

    runs: list[dict] = []
    recalls: dict[str, dict] = {}
    gen_fps: dict[str, list[float]] = {}
    t_start = time.perf_counter()
    try:
        for sc in scenarios:
            for seed in seeds:
                seq, gfps = sequence(cache, sc, args.frames, seed, size)
                if gfps is not None:
                    gen_fps.setdefault(sc, []).append(round(gfps, 2))
                jobs: list[tuple[str, str]] = []
                if "none" in maskers:
                    jobs.append(("none", "none"))
                jobs += [("oracle", m) for m in maskers if m not in ("none", "gt")]
                if "gt" in maskers:
                    jobs.append(("gt", "gt"))
                if seed in det_seeds:
                    for name, det in detectors.items():
                        rec = detector_recall(det, seq)
                        rec["fires"] = rec["recall"] is not None and rec["recall"] >= args.min_recall
                        rec["seed"] = seed
                        recalls.setdefault(sc, {})[name] = rec
                        print(f"[{sc} seed {seed}] {name}: recall {fmt(rec['recall'], '.2f')} "
                              f"({rec['matched']}/{rec['objects']}) {rec['per_label']}", flush=True)
                        if rec["fires"]:
                            jobs += [(name, m) for m in maskers if m not in ("none", "gt")]
                for det, m in jobs:
                    t0 = time.perf_counter()
                    rec = slam_run(seq, work, det, m, seed, models)
                    rec.update(scenario=sc, seed=seed, detector=det, masker=m, frames=args.frames)
                    if det in ("oracle", "gt"):
                        rec["recall"] = 1.0
                    elif det != "none":
                        rec["recall"] = recalls[sc][det]["recall"]
                    runs.append(rec)
                    print(f"[{sc} seed {seed}] {det:11s} {m:8s} ATE {rec['ate_rmse']:.3f} m  drift {rec['drift_percent']:.2f}%  "
                          f"IoU {fmt(rec['iou_left'])}/{fmt(rec['iou_right'])}  {rec['fps']:.1f} FPS  lost {rec['lost']}  "
                          f"({time.perf_counter() - t0:.0f} s)", flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)

    summary = summarize(runs)
    tgt = targets(runs, summary)
    print_tables(summary, tgt, recalls, args.frames, size)
    out = {
        "benchmark": "synth_slam",
        "frames": args.frames,
        "size": list(size),
        "seeds": seeds,
        "detector_seeds": det_seeds,
        "maskers": maskers,
        "generator_version": generator_version(),
        "generation_fps": gen_fps,
        "notes": notes,
        "targets_definition": {
            "ate_outline_over_none_max": TARGET_RATIO_NONE,
            "ate_outline_over_static_max": TARGET_RATIO_STATIC,
            "iou_gain_min": TARGET_IOU_GAIN,
            "iou_objects": f"nearer than {MAX_DISTANCE} m, >= {MIN_PIXELS} px",
        },
        "machine": machine(),
        "wall_s": round(time.perf_counter() - t_start, 1),
        "summary": summary,
        "targets": tgt,
        "detector_recall": recalls,
        "runs": runs,
    }
    write_json(args.out, out)
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
