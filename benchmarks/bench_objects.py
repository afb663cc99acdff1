"""Benchmark every object's track in the world (``objects/world.py``) and the motion test on real movers.

Two parts, each from ``dynastereo.api.run_sequence`` runs of the whole pipeline:

* **Synthetic** scenes with exact object trajectories (``gt/objects.json``: ``position``,
  the centre of the object's 3-D box in the first camera's frame, and ``speed``):
  ``--scenarios`` (default mixed, crossing, convoy) on ``--seeds`` (default 1,2,3; the
  objects module was developed on seeds 10-12 only), ground-truth **oracle** boxes (track
  id = GT id).  Per object-frame with an estimate: the position error in the frame's camera
  (``objects.jsonl`` ``camera`` against ``position_cam``: what the objects module measures;
  the error of ``world`` against ``position``, which adds SLAM's drift, is reported beside)
  and, for movers (GT ``moving``), the speed error (``speed`` against GT ``speed``) after
  the track's first 5 frames (the filter's start).  Medians by distance band
  (< 15, 15-30, 30-50 m) and for all objects within 30 m; and what was missed: the
  object-frames within 30 m the run reports without a position, their share, and the
  median with each of them counted as a miss (an infinite error) -- the figure the
  position target is judged on.
* **KITTI raw drive 0001** (an oncoming tram, cyclists, a passing car, parked cars), the
  default detector: the motion test's verdicts (``objects.jsonl`` of a default run)
  against the reference labels ``tests/data/raw0001_motion_labels.json`` (made by
  ``make_labels`` below from the reference masks, the stereo disparity inside them and the
  OXTS ground truth; checked by eye), for reference objects >= 300 px: object-frames
  right / undecided / wrong, movers masked within 3 frames of their first appearance,
  statics left unmasked.  And the ATE (APE RMSE, SE(3)-aligned) and end-point drift of the
  default run, ``--masker none`` and ``--mask-all`` against the OXTS ground truth (at the
  images' stamps, the default; beside it against the devkit's poses at the packets'), each
  run once per ``slam.n_features`` variant (2000, 1950, 2050, 2100; see
  ``bench_moving.py``: a short clip's ATE moves with such small changes), medians.

Targets: position error median <= 0.3 m (objects within 30 m, misses counted); speed error
median <= 0.3 m/s (movers); raw 0001 verdicts right >= 90 % of the decided object-frames;
default ATE median <= none's and <= 0.058 m; drift <= 0.25 %; the objects stage <= 1 ms
per frame.

Prints tables of medians; writes benchmarks/results/objects.json.  Run:

    DYNASTEREO_DATA=/work/shared/data DYNASTEREO_MODELS=/work/shared/models \\
        .venv/bin/python benchmarks/bench_objects.py [--seeds 1,2,3] [--quick]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from _common import data_dir, machine, median, models_dir, results_path, write_json
from _shared_runs import RAW_LABELS as LABELS  # raw 0001's reference labels
from _shared_runs import score_raw_labels as score_verdicts  # their scoring (tests use it from here)
from _shared_runs import sequence  # the cached synthetic sequences
from dynastereo.api import run_sequence
from dynastereo.config import Config
from dynastereo.eval import evaluate_files
from dynastereo.synth import read_objects

OUT = results_path("objects")
DRIVE = Path("kitti_raw") / "2011_09_26" / "2011_09_26_drive_0001_sync"
BANDS = ((0.0, 15.0), (15.0, 30.0), (30.0, 50.0))
NEAR = 30.0
SPEED_SKIP = 5
TARGETS = {"position_m": 0.3, "speed_mps": 0.3, "verdicts_right": 0.90, "ate_m": 0.058, "drift_percent": 0.25,
           "objects_ms": 1.0}
MODES = {"default": {}, "none": {"masker.kind": "none"}, "mask_all": {"motion.mode": "all"}}


def _median(v):
    return median(v, finite=True)


def _objects_lines(run_dir: Path):
    for line in (run_dir / "objects.jsonl").read_text().splitlines():
        if line.strip():
            yield json.loads(line)


def synth_errors(run_dir: Path, seq_dir: Path) -> dict:
    """Position and speed errors of ``run_dir/objects.jsonl`` against ``gt/objects.json`` (module doc)."""
    gt = read_objects(seq_dir)
    rows = []  # (distance, position error, speed error or nan, moving, world error, object id)
    seen: dict[int, int] = {}
    unplaced = []  # (distance, object id) of the object-frames the run reports without a position
    for rec in _objects_lines(run_dir):
        f = int(rec["frame"])
        g = {o.id: o for o in gt.frame(f)}
        for o in rec["objects"]:
            go = g.get(int(o["track"]))
            if go is None:
                continue
            if "world" not in o:
                unplaced.append((go.distance, go.id))
                continue
            seen[go.id] = seen.get(go.id, 0) + 1
            err = float(np.linalg.norm(np.subtract(o["camera"], go.position_cam)))
            werr = float(np.linalg.norm(np.subtract(o["world"], go.position)))
            sp = o.get("speed")
            serr = abs(sp - go.speed) if (go.moving and sp is not None and seen[go.id] > SPEED_SKIP) else np.nan
            rows.append((go.distance, err, serr, go.moving, werr, go.id))
    a = np.array(rows, float).reshape(-1, 6)
    u = np.array(unplaced, float).reshape(-1, 2)
    out = {"object_frames": len(a)}
    for lo, hi in BANDS:
        m = (a[:, 0] >= lo) & (a[:, 0] < hi)
        out[f"position_m_{lo:.0f}_{hi:.0f}"] = _median(a[m, 1])
        out[f"n_{lo:.0f}_{hi:.0f}"] = int(m.sum())
    near = a[:, 0] < NEAR
    out["position_m_near"] = _median(a[near, 1])
    # what was missed: the object-frames within 30 m the run reports without a position
    # (no disparity on most of the outline, a lost pose); the median above is over the rest
    n_unplaced = int((u[:, 0] < NEAR).sum())
    out["unplaced_near"] = n_unplaced
    out["placed_fraction_near"] = float(near.sum() / max(near.sum() + n_unplaced, 1))
    # the median with every unplaced object-frame counted as a miss (an infinite error):
    # the placed errors' quantile at 0.5 / placed fraction
    q = 0.5 / out["placed_fraction_near"] if near.any() else 2.0
    out["position_m_near_misses_counted"] = float(np.quantile(a[near, 1], q)) if q <= 1.0 else None
    out["position_m_p90_near"] = float(np.percentile(a[near, 1], 90)) if near.any() else None
    out["world_position_m_near"] = _median(a[near, 4])  # through SLAM's own poses: its drift included
    out["speed_mps_movers"] = _median(a[:, 2])
    out["speed_mps_movers_near"] = _median(a[near, 2])
    out["speed_frames"] = int(np.isfinite(a[:, 2]).sum())
    # kept for the pooled figures (main() pools them over the runs, drops them from the JSON):
    # the near errors with each unplaced near object-frame as inf, and their object ids
    un = u[u[:, 0] < NEAR]
    out["_near_errors"] = np.concatenate([a[near, 1], np.full(len(un), np.inf)])
    out["_near_ids"] = np.concatenate([a[near, 5], un[:, 1]]).astype(np.int64)
    out["_speed_errors"] = a[np.isfinite(a[:, 2]), 2]
    return out


def pooled_position(synth: list[dict]) -> dict:
    """The position error's median read two more ways than the median of the runs' medians
    (which weighs a run of 3 objects as one of 17): over every near object-frame of every
    run, and over objects (each object's median over its near frames; misses counted as
    infinite errors in both); and the speed error's median over every mover-frame."""
    errs = np.concatenate([r["_near_errors"] for r in synth]) if synth else np.zeros(0)
    per_object = []
    for r in synth:
        for i in np.unique(r["_near_ids"]):
            per_object.append(float(np.median(r["_near_errors"][r["_near_ids"] == i])))
    speeds = np.concatenate([r["_speed_errors"] for r in synth]) if synth else np.zeros(0)
    return {"object_frames_near": int(len(errs)), "objects_near": len(per_object),
            "mover_frames_speed_median": float(np.median(speeds)) if len(speeds) else None,
            "object_frames_median_misses_counted": float(np.median(errs)) if len(errs) else None,
            "objects_median_misses_counted": float(np.median(per_object)) if per_object else None}


def objects_ms(run_dir: Path) -> float | None:
    s = json.loads((run_dir / "timing.json").read_text())["summary"]
    return s.get("objects", {}).get("median")


REUSE = False  # --reuse: a finished run folder (run.json without an error) is read, not run again


def replay_cost(seq_dir: Path, run_dir: Path, detector: str | None, frames: int = 60, repeats: int = 3,
                settings: dict | None = None, compare: dict | None = None) -> dict:
    """The objects stage alone (the pipeline's own stage times include the waits of a
    masking thread on shared cores): the masks of the first ``frames`` frames made once
    (with the run's motion verdicts and speeds from its ``objects.jsonl``), then
    ``WorldObjects.update`` with the run's poses timed ``repeats`` times, as the calling
    thread's CPU time (``ms_*``: what the stage costs, unaffected by other processes on a
    busy machine) and wall time (``wall_ms_*``); per frame the fastest repeat, then ms per
    frame (median, p90) over the frames.  ``compare``: more overrides for a second tracker
    timed alternately with the first over the same masks (``compared``: its figures)."""
    from dynastereo.eval.trajectory import read_trajectory
    from dynastereo.io import open_sequence
    from dynastereo.masking import build_masker
    from dynastereo.objects.world import WorldObjects

    cfg = Config().with_overrides({**(settings or {}), **({"detector.name": detector} if detector else {})})
    seq = open_sequence(seq_dir)
    masker = build_masker(cfg, seq.calibration, models_dir=models_dir(required=False), ground_truth=seq_dir)
    poses = read_trajectory(run_dir / "trajectory.kitti.txt").poses
    recs = {r["frame"]: r["objects"] for r in _objects_lines(run_dir)}
    n = min(frames, len(seq), len(poses))
    data = []
    for i in range(n):
        frame = seq.frame(i)
        m = masker.mask(frame)
        for o, r in zip(m.objects, recs.get(i, [])):
            o.moving, o.speed_mps, o.speed_sigma_mps = r.get("moving"), r.get("speed_mps"), r.get("speed_sigma_mps")
        data.append((m, frame))
    stamps = seq.timestamps()
    cfgs = [cfg] + ([cfg.with_overrides(compare)] if compare else [])
    times = np.zeros((len(cfgs), repeats, n, 2))  # (CPU of this thread, wall) ms
    for r in range(repeats):
        for c, cf in enumerate(cfgs):  # alternated: both see the same machine
            wo = WorldObjects.from_config(seq.calibration, cf)
            for i, (m, frame) in enumerate(data):
                c0, t0 = time.thread_time(), time.perf_counter()
                wo.update(m, poses[i], True, float(stamps[i]), frame)
                times[c, r, i] = (time.thread_time() - c0) * 1e3, (time.perf_counter() - t0) * 1e3
    q = lambda v: round(float(v), 3)  # noqa: E731

    def figures(t: np.ndarray) -> dict:
        cpu, wall = t.min(axis=0).T
        return {"ms_median": q(np.median(cpu)), "ms_p90": q(np.percentile(cpu, 90)),
                "wall_ms_median": q(np.median(wall)), "wall_ms_p90": q(np.percentile(wall, 90))}

    out = {"frames": n, "repeats": repeats, "objects_median": float(np.median([len(m.objects) for m, _ in data])),
           **figures(times[0]), "loadavg": round(os.getloadavg()[0], 2)}
    if compare:
        out["compared"] = {"settings": compare, **figures(times[1])}
    return out


def run(seq_dir: Path, out: Path, detector: str | None = None, **settings) -> dict:
    done = out / "run.json"
    if REUSE and done.is_file():
        r = json.loads(done.read_text())
        if "error" not in r:
            return {"frames": r.get("frames_done"), "lost": r.get("frames_lost"),
                    "wall_s": r.get("wall_s"), "reused": True}
    over = dict(settings)
    if detector:
        over["detector.name"] = detector
    cfg = Config().with_overrides(over)
    t0 = time.perf_counter()
    res = run_sequence(seq_dir, out, cfg, stereo_check=False, overwrite=True)
    return {"frames": len(res.frames), "lost": len(res.lost), "wall_s": round(time.perf_counter() - t0, 2)}


def accuracy(run_dir: Path, gt: Path, gt_packets: Path | None = None) -> dict:
    """ATE and drift against ``gt`` (the OXTS poses at the images' stamps) and, given
    ``gt_packets`` (a TUM file of the devkit's, at the packets' stamps), against those too."""
    ev = evaluate_files(run_dir / "trajectory.kitti.txt", gt)
    r = {"ate_m": round(float(ev.ape["rmse"]), 4), "drift_percent": round(float(ev.drift_percent), 3)}
    if gt_packets is not None:
        ev = evaluate_files(run_dir / "trajectory.kitti.txt", gt_packets)
        r |= {"ate_m_packets": round(float(ev.ape["rmse"]), 4),
              "drift_percent_packets": round(float(ev.drift_percent), 3)}
    return r


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenarios", default="mixed,crossing,convoy")
    ap.add_argument("--seeds", default="1,2,3", help="seeds for the synthetic part (10 was developed on)")
    ap.add_argument("--frames", type=int, default=150, help="frames per synthetic sequence")
    ap.add_argument("--size", default="640x192")
    ap.add_argument("--raw", type=int, default=1, help="1: also the KITTI raw 0001 part")
    ap.add_argument("--variants", default="2000,1950,2050,2100", help="slam.n_features per raw 0001 run")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "dynastereo_bench_synth")
    ap.add_argument("--work", type=Path, default=None, help="run folders (default: a new temporary folder)")
    ap.add_argument("--quick", action="store_true", help="one seed, mixed only, one raw variant")
    ap.add_argument("--reuse", action="store_true", help="reuse finished runs in --work (e.g. after an interruption)")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a configuration override for every run, e.g. objects.block_size=0 (repeatable)")
    ap.add_argument("--cost-compare", action="append", default=None, metavar="KEY=VALUE",
                    help="the objects stage's cost also measured with these overrides, alternately over the same "
                         "masks (default: objects.block_size=0, the masker's disparity; 'none': no comparison)")
    args = ap.parse_args()
    try:
        settings = {k: yaml.safe_load(v) for k, v in (kv.split("=", 1) for kv in args.set)}
        pairs = [kv for kv in args.cost_compare or ["objects.block_size=0"] if kv != "none"]
        compare = {k: yaml.safe_load(v) for k, v in (kv.split("=", 1) for kv in pairs)}
    except ValueError:
        ap.error(f"--set / --cost-compare take KEY=VALUE, got {args.set + (args.cost_compare or [])}")
    if args.quick:
        args.seeds, args.scenarios, args.variants = "1", "mixed", "2000"
    global REUSE
    REUSE = args.reuse
    logging.basicConfig(level=logging.ERROR)
    logging.getLogger("dynastereo").setLevel(logging.ERROR)
    size = tuple(int(v) for v in args.size.split("x"))
    args.cache.mkdir(parents=True, exist_ok=True)
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_objects_"))
    work.mkdir(parents=True, exist_ok=True)
    seeds = [int(s) for s in args.seeds.split(",") if s]

    synth = []
    for sc in [s for s in args.scenarios.split(",") if s]:
        for seed in seeds:
            seq, _ = sequence(args.cache, sc, args.frames, seed, size)
            out = work / f"{sc}_s{seed}"
            row = {"scenario": sc, "seed": seed, **run(seq, out, "oracle", **settings), **synth_errors(out, seq),
                   "objects_ms": objects_ms(out)}
            synth.append(row)
            print(f"{sc:9s} seed {seed}: position {row['position_m_near']:.3f} m (< {NEAR:.0f} m, "
                  f"{row['n_0_15'] + row['n_15_30']} object-frames placed, {row['unplaced_near']} not), "
                  f"speed {row['speed_mps_movers']} m/s "
                  f"({row['speed_frames']} mover-frames); objects stage {row['objects_ms']} ms/frame", flush=True)

    raw = None
    data = data_dir(required=False)
    if data and args.raw:
        raw = raw_part(Path(data) / DRIVE, work, [int(v) for v in args.variants.split(",") if v], settings)
    # the objects stage alone, replayed (the in-pipeline stage times include a busy masking thread's waits)
    replays = {}
    for first in [r for r in synth if r["seed"] == seeds[0]]:  # each scenario's first seed
        seq, _ = sequence(args.cache, first["scenario"], args.frames, first["seed"], size)
        replays[f"synth {first['scenario']} seed {first['seed']}"] = replay_cost(
            seq, work / f"{first['scenario']}_s{first['seed']}", "oracle", settings=settings, compare=compare)
    if raw:
        nf = raw["runs"]["default"][0]["n_features"]
        replays["KITTI raw 0001"] = replay_cost(Path(data) / DRIVE, work / f"raw0001_default_nf{nf}", None,
                                                settings=settings, compare=compare)
    for k, v in replays.items():
        other = f"; {v['compared']['settings']}: {v['compared']['ms_median']}" if "compared" in v else ""
        print(f"objects stage alone, {k}: {v['ms_median']} ms/frame median (p90 {v['ms_p90']}){other}, "
              f"{v['objects_median']:.0f} objects a frame", flush=True)

    # the target counts what was missed: an object-frame within 30 m without a position is a miss
    pos = _median([r["position_m_near_misses_counted"] for r in synth])
    pos_placed = _median([r["position_m_near"] for r in synth])
    pooled = pooled_position(synth)
    for r in synth:
        del r["_near_errors"], r["_near_ids"], r["_speed_errors"]
    placed = _median([r["placed_fraction_near"] for r in synth])
    spd = _median([r["speed_mps_movers"] for r in synth])
    ms_worst = max((v["ms_median"] for v in replays.values()), default=None)
    ms_pipeline = [r["objects_ms"] for r in synth] + ([raw["objects_ms"]] if raw else [])
    targets = {
        "position_m": {"value": pos, "target": TARGETS["position_m"], "met": pos is not None and pos <= 0.3,
                       "counts": "misses (object-frames within 30 m without a position) as errors",
                       "placed_only": pos_placed, "placed_fraction_near": placed,
                       "median_of": "the runs' medians (each run's object-frames within 30 m)",
                       "pooled": pooled},
        "speed_mps": {"value": spd, "target": TARGETS["speed_mps"], "met": spd is not None and spd <= 0.3},
        "objects_ms": {"value": ms_worst, "target": 1.0, "met": ms_worst is not None and ms_worst <= 1.0,
                       "in_pipeline_medians": ms_pipeline},
    }
    if raw and raw["verdicts"]:
        v = raw["verdicts"]
        targets["verdicts_right"] = {"value": v["right_of_decided"], "target": 0.9,
                                     "met": v["right_of_decided"] is not None and v["right_of_decided"] >= 0.9}
        targets["movers_masked_within_3"] = {"value": v["movers_masked_within_3"], "target": v["movers"],
                                             "met": v["movers_masked_within_3"] == v["movers"]}
    if raw:
        d, n = raw["accuracy"]["default"], raw["accuracy"]["none"]
        targets["ate_default_le_none"] = {"value": [d["ate_m"], n["ate_m"]], "met": d["ate_m"] <= n["ate_m"]}
        targets["ate_m"] = {"value": d["ate_m"], "target": 0.058, "met": d["ate_m"] <= 0.058}
        targets["drift_percent"] = {"value": d["drift_percent"], "target": 0.25, "met": d["drift_percent"] <= 0.25,
                                    "ground_truth": "OXTS poses at the images' stamps",
                                    "at_packets": d["drift_percent_packets"],
                                    "met_at_packets": d["drift_percent_packets"] <= 0.25}

    if synth:  # (--scenarios "": the raw 0001 part alone)
        print_synth(args.seeds, synth, pos, pooled)
    if raw:
        print_raw(raw)
    for k, t in targets.items():
        print(f"target {k}: {'met' if t['met'] else 'NOT met'} ({t})")
    result = {
        "benchmark": "objects",
        "machine": machine(),
        "config": {"frames": args.frames, "size": args.size, "seeds": seeds, "developed_on_seeds": [10, 11, 12],
                   "n_features": args.variants, "settings": settings},
        "synthetic": synth,
        "synthetic_medians": {"position_m_near": pos_placed, "speed_mps_movers": spd,
                              "placed_fraction_near": placed, "position_m_near_misses_counted": pos,
                              "unplaced_near_total": sum(r["unplaced_near"] for r in synth),
                              "pooled": pooled,
                              "world_position_m_near": _median([r["world_position_m_near"] for r in synth])},
        "replay_cost": replays,
        "kitti_raw_0001": raw,
        "targets": targets,
    }
    write_json(args.out, result, default=float)
    print(f"-> {args.out}")
    return 0


def print_synth(seeds: str, synth: list[dict], pos: float | None, pooled: dict) -> None:
    """The synthetic part's table of medians (main)."""
    print(f"\nsynthetic, oracle boxes, seeds {seeds}: medians over the seeds")
    print(f"{'scenario':10s} {'<15 m':>7s} {'15-30 m':>8s} {'30-50 m':>8s} {'<30 m':>7s} {'placed':>7s} "
          f"{'<30 m*':>7s} {'speed':>7s} {'ms':>6s}   (* misses counted)")
    for sc in dict.fromkeys(r["scenario"] for r in synth):
        rs = [r for r in synth if r["scenario"] == sc]
        cells = [_median([r[k] for r in rs]) for k in ("position_m_0_15", "position_m_15_30", "position_m_30_50",
                                                          "position_m_near", "placed_fraction_near",
                                                          "position_m_near_misses_counted", "speed_mps_movers",
                                                          "objects_ms")]
        print(f"{sc:10s} " + " ".join(f"{'-' if c is None else f'{c:.3f}':>7s}" for c in cells))
    print(f"position within 30 m, misses counted: median of the runs' medians {pos:.3f} m; over all "
          f"{pooled['object_frames_near']} object-frames {pooled['object_frames_median_misses_counted']:.3f} m; "
          f"over {pooled['objects_near']} objects (each its median) {pooled['objects_median_misses_counted']:.3f} m; "
          f"speed over all mover-frames {pooled['mover_frames_speed_median']:.3f} m/s")


# ------------------------------------------------------------------ KITTI raw 0001


def raw_part(drive: Path, work: Path, variants: list[int], settings: dict | None = None) -> dict:
    """The verdicts of the default run (first variant) against the reference labels, and
    ATE / drift of default, none and mask-all per ``slam.n_features`` variant (module doc)."""
    from dynastereo.api import write_ground_truth
    from dynastereo.eval.trajectory import find_ground_truth

    gt = find_ground_truth(drive)
    gt_packets = work / "gt_packets.tum.txt"
    write_ground_truth(drive, gt_packets, "tum", at="packets")
    runs: dict[str, list[dict]] = {m: [] for m in MODES}
    for nf in variants:
        for mode, over in MODES.items():
            out = work / f"raw0001_{mode}_nf{nf}"
            r = {"n_features": nf, **run(drive, out, None, **(settings or {}), **over, **{"slam.n_features": nf}),
                 **accuracy(out, gt, gt_packets)}
            if mode == "default":
                r["objects_ms"] = objects_ms(out)
            runs[mode].append(r)
            print(f"raw 0001 {mode:8s} n_features {nf}: ATE {r['ate_m']:.4f} m, drift {r['drift_percent']:.3f} % "
                  f"(at the packets' stamps {r['ate_m_packets']:.4f} m, {r['drift_percent_packets']:.3f} %)",
                  flush=True)
    acc = {m: {"ate_m": _median([r["ate_m"] for r in rs]), "drift_percent": _median([r["drift_percent"] for r in rs]),
               "ate_range": [min(r["ate_m"] for r in rs), max(r["ate_m"] for r in rs)],
               "drift_range": [min(r["drift_percent"] for r in rs), max(r["drift_percent"] for r in rs)],
               "ate_m_packets": _median([r["ate_m_packets"] for r in rs]),
               "drift_percent_packets": _median([r["drift_percent_packets"] for r in rs])}
           for m, rs in runs.items()}
    first = work / f"raw0001_default_nf{variants[0]}"
    verdicts = score_verdicts(first, LABELS) if LABELS.is_file() else None
    return {"runs": runs, "accuracy": acc, "verdicts": verdicts,
            "objects_ms": runs["default"][0]["objects_ms"]}


def print_raw(raw: dict) -> None:
    v = raw["verdicts"]
    if v:
        print("\nKITTI raw 0001: the motion test's verdicts (default run) against the reference labels, "
              "objects >= 300 px")
        print(f"object-frames {v['object_frames']}: right {v['right']}, undecided {v['undecided']}, wrong "
              f"{v['wrong']}; right of decided {v['right_of_decided']:.3f}")
        print(f"movers masked within 3 frames of first appearance: {v['movers_masked_within_3']} of {v['movers']}; "
              f"static object-frames left unmasked: {v['static_unmasked']} of {v['static_frames']}")
        print("by label:", json.dumps(v["by_label"]))
    print("\nKITTI raw 0001 vs OXTS: medians over the n_features variants (range)")
    for m, a in raw["accuracy"].items():
        print(f"  {m:9s} ATE {a['ate_m']:.4f} m ({a['ate_range'][0]:.4f}-{a['ate_range'][1]:.4f})  drift "
              f"{a['drift_percent']:.3f} % ({a['drift_range'][0]:.3f}-{a['drift_range'][1]:.3f});  against the "
              f"devkit's poses at the packets' stamps: ATE {a['ate_m_packets']:.4f} m, drift "
              f"{a['drift_percent_packets']:.3f} %")


# ------------------------------------------------------------------ the reference labels


LABEL_CLASSES = {"car", "truck", "bus", "person", "bicycle", "motorcycle", "train"}
SIGMA_D = 0.5  # px, the disparity's noise for the labels' depth uncertainty
MOVING_MPS = 2.0  # a track faster than this (and 3 sigma) is moving


def _ref_frame(ref_dir: Path, f: int):
    import cv2

    ids = cv2.imread(str(ref_dir / f"{f:06d}.png"), cv2.IMREAD_UNCHANGED)
    meta = json.loads((ref_dir / f"{f:06d}.json").read_text())
    return ids, meta["instances"]


def make_labels(drive: Path, ref_dir: Path, out: Path, overlays: Path | None = None) -> dict:
    """The reference labels of raw 0001 (module doc): per reference instance (vehicles,
    persons, bikes) and frame, its world position from its mask (median disparity of a
    plain SGBM inside it -> depth, mask centroid -> ray) and the OXTS pose; instances
    associated across frames by box IoU >= 0.3 with the last box of a track of the same
    class group seen within 2 frames (greedy, best IoU first); each track labelled from a
    least-squares line through its world positions in the frames where its box is clear of
    the image's sides (horizontal speed, its sigma from the depth noise ``SIGMA_D`` and 0.3 m
    of centroid wander): moving when faster than ``MOVING_MPS`` and 3 sigma, static when
    ``MOVING_MPS`` is more than 2 sigma above its speed, else undecided (not scored)."""
    import cv2

    from dynastereo.io import open_sequence
    from dynastereo.masking.boxes import box_iou
    from dynastereo.objects.motion.verdicts import _group

    seq = open_sequence(drive)
    c = seq.calibration
    gt = __import__("dynastereo.eval.trajectory", fromlist=["read_trajectory"]).read_trajectory(drive)
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=128, blockSize=5, P1=8 * 25, P2=32 * 25,
                                 uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
                                 mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    tracks: list[dict] = []
    for f in range(len(seq)):
        fr = seq.frame(f)
        disp = sgbm.compute(fr.left_gray, fr.right_gray).astype(np.float32) / 16.0
        ids, inst = _ref_frame(ref_dir, f)
        T = gt.poses[f]
        dets = []
        for o in inst:
            if o["class"] not in LABEL_CLASSES:
                continue
            m = ids == o["id"]
            d = disp[m & (disp > 0.5)]
            if d.size < 10:
                continue
            dm = float(np.median(d))
            ys, xs = np.nonzero(m)
            z = c.bf / dm
            X = np.array([(xs.mean() - c.cx) * z / c.fx, (ys.mean() - c.cy) * z / c.fy, z])
            sz = z * SIGMA_D / dm
            dets.append({"box": o["box"], "label": o["class"], "px": int(m.sum()), "cam": X,
                         "world": T[:3, :3] @ X + T[:3, 3], "sigma_z": sz, "R": T[:3, :3]})
        live = [t for t in tracks if f - t["frames"][-1] <= 2]
        used_t, used_d = set(), set()
        if live and dets:
            iou = box_iou([t["boxes"][-1] for t in live], [d["box"] for d in dets])
            for a, b in sorted(np.argwhere(iou >= 0.3).tolist(), key=lambda ab: -iou[ab[0], ab[1]]):
                if a in used_t or b in used_d or _group(live[a]["label"]) != _group(dets[b]["label"]):
                    continue
                used_t.add(a)
                used_d.add(b)
                t, d = live[a], dets[b]
                t["frames"].append(f)
                for k, v in (("boxes", d["box"]), ("pixels", d["px"]), ("world", d["world"]),
                             ("sigma_z", d["sigma_z"]), ("ray", d["R"] @ (d["cam"] / np.linalg.norm(d["cam"])))):
                    t[k].append(v)
        for b, d in enumerate(dets):
            if b not in used_d:
                tracks.append({"id": len(tracks) + 1, "label": d["label"], "frames": [f], "boxes": [d["box"]],
                               "pixels": [d["px"]], "world": [d["world"]], "sigma_z": [d["sigma_z"]],
                               "ray": [d["R"] @ (d["cam"] / np.linalg.norm(d["cam"]))]})
    stamps = seq.timestamps()
    objects = []
    for t in tracks:
        # the fit leaves out the frames where the box touches the image's side (a cut view:
        # its centroid wanders along the body)
        whole = np.array([b[0] > 2 and b[2] < c.width - 2 for b in t["boxes"]])
        W = np.array(t["world"])[whole]
        ts = stamps[np.array(t["frames"])][whole]
        t["sigma_z"] = list(np.array(t["sigma_z"])[whole])
        rec = {"id": t["id"], "label": t["label"], "frames": t["frames"],
               "boxes": [[round(float(v), 1) for v in b] for b in t["boxes"]], "pixels": t["pixels"]}
        if len(W) >= 3 and ts[-1] - ts[0] >= 0.25:
            # least squares x(t), z(t); the position's sigma along each frame's ray -> per-axis weights
            A = np.column_stack([np.ones_like(ts), ts - ts.mean()])
            sig = np.array(t["sigma_z"]) + 0.3  # + the centroid's wander on the body (metres)
            v, sv = np.zeros(2), np.zeros(2)
            for j, ax in enumerate((0, 2)):
                w = 1.0 / sig**2
                cov = np.linalg.inv(A.T @ (A * w[:, None]))
                coef = cov @ (A.T @ (w * W[:, ax]))
                v[j], sv[j] = coef[1], np.sqrt(cov[1, 1])
            speed = float(np.hypot(*v))
            s_sig = float(np.hypot(*(sv * np.abs(v))) / speed) if speed > 1e-6 else float(sv.max())
            moving = (True if speed > MOVING_MPS and speed > 3 * s_sig
                      else (False if speed + 2 * s_sig < MOVING_MPS else None))
            rec.update(speed=round(speed, 2), speed_sigma=round(s_sig, 2), moving=moving,
                       moved_m=round(float(np.linalg.norm(W[-1, [0, 2]] - W[0, [0, 2]])), 2))
        else:
            rec.update(speed=None, speed_sigma=None, moving=None, moved_m=None)
        objects.append(rec)
    labels = {"drive": drive.name, "reference": str(ref_dir.name),
              "made_by": "benchmarks/bench_objects.py --make-labels",
              "method": make_labels.__doc__.split("\n\n")[0] if make_labels.__doc__ else "",
              "thresholds": {"moving_mps": MOVING_MPS, "sigma_disparity_px": SIGMA_D},
              "classes": sorted(LABEL_CLASSES), "objects": objects}
    write_json(out, labels, indent=None, separators=(",", ":"))
    if overlays is not None:
        draw_label_overlays(seq, labels, overlays)
    return labels


def draw_label_overlays(seq, labels: dict, folder: Path, frames=(10, 30, 45, 60, 75, 90, 105)) -> list[Path]:
    """Frames with each labelled reference object's box in its label's colour (red moving,
    green static, orange undecided) and ``#id label speed``, to check by eye."""
    import cv2

    from dynastereo.viz.draw import VERDICT_COLOURS

    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for f in frames:
        img = cv2.cvtColor(seq.frame(f).left_gray, cv2.COLOR_GRAY2BGR)
        for o in labels["objects"]:
            if f not in o["frames"]:
                continue
            b = o["boxes"][o["frames"].index(f)]
            col = VERDICT_COLOURS[o["moving"]]
            cv2.rectangle(img, (int(b[0]), int(b[1])), (int(b[2]), int(b[3])), col, 2)
            sp = "" if o["speed"] is None else f" {o['speed']:.1f}"
            cv2.putText(img, f"#{o['id']} {o['label']}{sp}", (int(b[0]), max(int(b[1]) - 3, 10)),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.45, col, 1, cv2.LINE_AA)
        p = folder / f"labels_raw0001_{f:03d}.png"
        cv2.imwrite(str(p), img)
        out.append(p)
    return out


if __name__ == "__main__":
    if "--make-labels" in sys.argv:
        data = data_dir()
        ref = data.parent / "reference" / "refmasks" / "raw_0001"
        i = sys.argv.index("--make-labels") + 1
        ov = Path(sys.argv[i]) if len(sys.argv) > i else None
        lab = make_labels(data / DRIVE, ref, LABELS, ov)
        for o in lab["objects"]:
            if max(o["pixels"]) >= 300 and len(o["frames"]) >= 3:
                print(o["id"], o["label"], o["frames"][0], "-", o["frames"][-1], "px max", max(o["pixels"]),
                      "speed", o["speed"], "+-", o["speed_sigma"], "moved", o["moved_m"], "->", o["moving"])
        sys.exit(0)
    sys.exit(main())
