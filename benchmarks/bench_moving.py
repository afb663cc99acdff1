"""Benchmark the per-object motion test ("mask only what moves", ``objects/motion``).

Four parts, each a ``dynastereo.api.run_sequence`` of the whole pipeline (masking on
the prefetch thread, stereo SLAM with local BA):

* **Decisions** on the synthetic scenarios (``--scenarios``, default mixed, static,
  convoy, crossing, oncoming) with the ground-truth **oracle** boxes (track id = GT id),
  on ``--seeds`` (default 1-6; the thresholds were tuned on seed 0 only), scored by
  :func:`dynastereo.eval.verdicts.score_verdicts` from the ground truth: an object-frame
  counts when the object has at least 300 visible left pixels and is past its first 3
  frames in view; it is right when a reported box matches it with IoU >= 0.5 and its
  ``moving`` equals the ground truth's (unmatched and ``null``, undecided, count as
  wrong).  Per scenario the rate pooled over the seeds (and each seed's), the undecided
  fraction, and the moving objects judged static (the costly error); beside them, KITTI
  raw 0001's verdicts against its reference labels (``bench_objects.score_verdicts``: right
  of the decided object-frames).  ``--verdicts-only`` runs just these two and writes
  ``results/motion_verdicts.json``; with ``--old-commit C`` it also runs commit C's ``src``
  (``git archive``, each run in its own process) on the same sequences, scored by this
  checkout's scorer, and prints the pooled rates and each seed's side by side
  (``results/motion_verdicts_then_now.json``: 6fb24c0 against this code on mixed seeds
  1-6); ``--gt-poses`` replays the masker and the motion test with the ground-truth poses
  instead of running the SLAM (``results/motion_verdicts_gt_poses.json``: the verdicts of
  the masking and motion code alone, both commits).
* **ATE** (APE RMSE after SE(3) alignment, ``dynastereo.eval.evaluate_files``) with
  masking ``none`` / ``all`` (the thesis: every detection masked, ``motion.mode: all``) /
  ``moving`` (the default: moving and undecided objects masked) on KITTI 06 and 03 (the
  default detector, ``$DYNASTEREO_MODELS``) and on synthetic ``convoy`` and ``crossing``
  (oracle boxes, seeds ``--ate-seeds``).  The SLAM is deterministic, but a short KITTI
  clip's ATE moves by tens of per cent with small changes that should not matter (a
  few more or fewer ORB features: KITTI 06 masked 0.026-0.068 m), so each KITTI mode runs once per ``--kitti-variants``
  (``slam.n_features`` values, the first the default 2000) and the KITTI ratio is
  judged on the medians over them (the default's own run reported beside).
* **Cost**: the motion test's ms per frame, ``motion_flow`` (masking thread: corners +
  optical flow + lookups) + ``motion`` (tracking thread: the test and hysteresis),
  replayed alone 3 times (per frame the fastest) on the first 60 frames of KITTI 06 /
  03 (the default detector's boxes) and of the first seed's mixed / static (oracle
  boxes) -- the target is judged on the worst sequence's median; the runs' own
  ``timing.json`` medians (which include the waits of a masking thread beside the SLAM
  on shared cores) are reported beside.
* **KITTI raw drive 0001** (an oncoming tram, cyclists, a passing car, parked cars; no
  ground-truth poses): the decisions per label, and overlays of frames 30, 60, 90 written
  to ``docs/motion_raw0001_NNN.jpg`` (docs/guide/masking.md) to check by eye.

Targets: decisions >= 90 % on mixed (pooled over the seeds); KITTI ATE(moving) <= 1.10 x ATE(none);
convoy / crossing ATE(moving) <= ATE(none) / 3; motion_flow + motion <= 3 ms per frame.

Prints tables of medians; writes benchmarks/results/moving.json.  Run:

    DYNASTEREO_DATA=/work/shared/data DYNASTEREO_MODELS=/work/shared/models \\
        .venv/bin/python benchmarks/bench_moving.py [--seeds 1,2,3,4,5,6] [--frames 150] [--quick]
        .venv/bin/python benchmarks/bench_moving.py --verdicts-only   # the verdict rates alone
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import ROOT, data_dir, machine, median, models_dir, results_path, write_json
from _shared_runs import RAW_LABELS, head_commit, old_tree, score_raw_labels, sequence
from dynastereo.api import run_sequence
from dynastereo.config import Config
from dynastereo.eval import evaluate_files
from dynastereo.eval.verdicts import VerdictScore, score_verdicts

OUT = results_path("moving")
OUT_VERDICTS = results_path("motion_verdicts")
MODES = ("none", "all", "moving")
TARGET_ACCURACY = 0.90
TARGET_KITTI_RATIO = 1.10
TARGET_SYNTH_RATIO = 1.0 / 3.0
TARGET_MS = 3.0
RAW_OVERLAY_FRAMES = (30, 60, 90)
DOCS = Path(__file__).resolve().parent.parent / "docs"


def decision_accuracy(run_dir: Path, seq_dir: Path) -> dict:
    """The verdicts in ``run_dir/objects.jsonl`` against ``seq_dir/gt/objects.json`` (module doc)."""
    v = score_verdicts(run_dir, seq_dir)
    n = v.object_frames
    return {**v.to_dict(), "accuracy": v.rate, "undecided_fraction": v.undecided / n if n else None}


def pooled_verdicts(rows: list[dict]) -> dict:
    """The counts of ``rows`` (``decision_accuracy``'s) added up, with the pooled rate."""
    fields = ("object_frames", "right", "undecided", "unmatched", "moving_judged_static", "static_judged_moving")
    total = VerdictScore(*(sum(r[k] for r in rows) for k in fields))
    rates = [r["accuracy"] for r in rows if r["accuracy"] is not None]
    return {**total.to_dict(), "seeds": len(rows), "seed_min": min(rates, default=None),
            "seed_median": _median(rates)}


def motion_ms(run_dir: Path) -> dict:
    s = json.loads((run_dir / "timing.json").read_text())["summary"]
    flow = s.get("motion_flow", {}).get("median")
    test = s.get("motion", {}).get("median")
    return {"motion_flow_ms": flow, "motion_ms": test,
            "total_ms": None if flow is None else round(flow + (test or 0.0), 3)}


def run(seq_dir: Path, out: Path, mode: str, detector: str | None, **settings) -> dict:
    over = {"masker.kind": "none"} if mode == "none" else {"motion.mode": mode}
    if detector:
        over["detector.name"] = detector
    over.update(settings)
    cfg = Config().with_overrides(over)
    t0 = time.perf_counter()
    res = run_sequence(seq_dir, out, cfg, stereo_check=False, overwrite=True)
    wall = time.perf_counter() - t0
    gt = seq_dir.parent.parent / "poses" / f"{seq_dir.name}.txt"
    ev = evaluate_files(out / "trajectory.kitti.txt", gt)
    row = {"mode": mode, "frames": len(res.frames), "ate_m": round(float(ev.ape["rmse"]), 4), "lost": len(res.lost),
           "wall_s": round(wall, 2)}
    if mode == "moving":
        row.update(motion_ms(out))
        row["map_points_forgotten"] = json.loads((out / "run.json").read_text())["motion"]["map_points_forgotten"]
    return row


def replay_cost(seq_dir: Path, run_dir: Path, detector: str | None, frames: int = 60, repeats: int = 3) -> dict:
    """The motion test's cost in isolation (the pipeline's own stage times include the
    waits of a masking thread sharing the cores with the SLAM): the masks of the first
    ``frames`` frames made once, then ``SceneFlow.measure`` and ``MotionJudge.update``
    (with the run's poses) timed alone, ``repeats`` times; per frame the fastest of the
    repeats (timeit's rule on a shared machine: the slower ones measured the other
    processes), then ms per frame (median, p90) over the frames."""
    from dynastereo.eval.trajectory import read_trajectory
    from dynastereo.io import open_sequence
    from dynastereo.masking import build_masker
    from dynastereo.objects.motion import MotionJudge, SceneFlow

    cfg = Config().with_overrides({"detector.name": detector} if detector else {})
    seq = open_sequence(seq_dir)
    masker = build_masker(cfg, seq.calibration, models_dir=models_dir(required=False),
                          ground_truth=seq_dir)
    poses = read_trajectory(run_dir / "trajectory.kitti.txt").poses
    n = min(frames, len(seq), len(poses))
    data = [(seq.frame(i), None) for i in range(n)]
    data = [(f, masker.mask(f)) for f, _ in data]
    times = np.zeros((repeats, n, 3))  # (flow, test, cpu) ms
    for r in range(repeats):
        flow, judge = SceneFlow(cfg.motion), MotionJudge(cfg.motion, seq.calibration)
        for i, (f, m) in enumerate(data):
            c0 = time.process_time()
            t0 = time.perf_counter()
            m.flow = flow.measure(f, m)
            t1 = time.perf_counter()
            judge.select(m)
            judge.update(m, poses[i][:3], ok=True)
            t2 = time.perf_counter()
            times[r, i] = (t1 - t0) * 1e3, (t2 - t1) * 1e3, (time.process_time() - c0) * 1e3
    best = times.min(axis=0)
    t_flow, t_test, cpu = best.T
    tot = (times[:, :, 0] + times[:, :, 1]).min(axis=0)
    q = lambda v: {"median": round(float(np.median(v)), 3), "p90": round(float(np.percentile(v, 90)), 3)}  # noqa: E731
    return {"frames": n, "repeats": repeats, "objects_median": float(np.median([len(m.objects) for _, m in data])),
            "motion_flow_ms": q(t_flow), "motion_ms": q(t_test), "total_ms": q(tot), "cpu_ms": q(cpu),
            "total_ms_first_repeat": q(times[0, :, 0] + times[0, :, 1]), "loadavg": round(os.getloadavg()[0], 2)}


def _median(v):
    return median(v)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenarios", default="mixed,static,convoy,crossing,oncoming")
    ap.add_argument("--seeds", default="1,2,3,4,5,6", help="seeds for the decisions (0 was tuned on)")
    ap.add_argument("--ate-seeds", default="1", help="seeds for the synthetic ATE runs")
    ap.add_argument("--frames", type=int, default=150, help="frames per synthetic sequence")
    ap.add_argument("--size", default="640x192")
    ap.add_argument("--kitti", default="06,03")
    ap.add_argument("--kitti-variants", default="2000,1950,2050,2100",
                    help="slam.n_features per KITTI run (the first: the default); ratios on their medians")
    ap.add_argument("--raw", type=int, default=1, help="1: also run KITTI raw drive 0001 (decisions only)")
    ap.add_argument("--overlays", type=int, default=1, help="1: write its overlays to docs/motion_raw0001_*.jpg")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "dynastereo_bench_synth")
    ap.add_argument("--quick", action="store_true", help="one seed, 60 frames, mixed + convoy, KITTI 06")
    ap.add_argument("--verdicts-only", action="store_true",
                    help="only the verdict rates: the synthetic decisions and raw 0001's (results/motion_verdicts.json)")
    ap.add_argument("--gt-poses", action="store_true",
                    help="with --verdicts-only: no SLAM; the masker and the motion test replayed with the sequences' "
                         "ground-truth poses (the verdicts of the masking and motion code alone)")
    ap.add_argument("--old-commit", default=None,
                    help="with --verdicts-only: also run this commit's src (git archive, its own process) on the same "
                         "sequences, scored by this checkout's scorer, paired per seed")
    ap.add_argument("--out", type=Path, default=None, help="the JSON written (default results/moving.json, "
                    "results/motion_verdicts.json with --verdicts-only)")
    args = ap.parse_args()
    args.out = args.out or (OUT_VERDICTS if args.verdicts_only else OUT)
    if args.quick:
        args.seeds, args.ate_seeds, args.frames, args.scenarios, args.kitti = "1", "1", 60, "mixed,convoy", "06"
        args.kitti_variants = "2000"
        args.raw = args.overlays = 0
    logging.basicConfig(level=logging.ERROR)
    logging.getLogger("dynastereo").setLevel(logging.ERROR)
    size = tuple(int(v) for v in args.size.split("x"))
    args.cache.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="bench_moving_"))
    seeds = [int(s) for s in args.seeds.split(",") if s]
    ate_seeds = [int(s) for s in args.ate_seeds.split(",") if s]

    decisions = []
    old_src = old_tree(args.old_commit, work / "old") if args.old_commit and args.verdicts_only else None
    then = []
    for sc in [s for s in args.scenarios.split(",") if s]:
        for seed in seeds:
            seq, _ = sequence(args.cache, sc, args.frames, seed, size)
            if old_src is not None:  # the old code first, then this checkout's, per sequence
                out = work / f"{sc}_s{seed}_old"
                then.append({"scenario": sc, "seed": seed, **run_tree(old_src, seq, out, args.gt_poses),
                             **decision_accuracy(out, seq)})
                print(f"{sc:9s} seed {seed} ({args.old_commit}): decisions {then[-1]['accuracy']:.3f}", flush=True)
            out = work / f"{sc}_s{seed}_moving"
            if args.gt_poses and args.verdicts_only:
                row = {"scenario": sc, "seed": seed, **run_tree(THIS_SRC, seq, out, True), **decision_accuracy(out, seq),
                       "ate_m": None, "total_ms": None}
            else:
                row = {"scenario": sc, "seed": seed, **run(seq, out, "moving", "oracle"), **decision_accuracy(out, seq)}
            if seed == seeds[0] and sc in ("mixed", "static") and not args.verdicts_only:
                row["replay"] = replay_cost(seq, out, "oracle")
            decisions.append(row)
            print(f"{sc:9s} seed {seed}: decisions {row['accuracy']:.3f} right of {row['object_frames']} object-frames"
                  f" (undecided {row['undecided_fraction']:.3f}, unmatched {row['unmatched']}, moving judged static "
                  f"{row['moving_judged_static']}, "
                  f"static judged moving {row['static_judged_moving']}); ATE {row['ate_m']} m; "
                  f"{row['total_ms']} ms/frame", flush=True)

    pooled = {sc: pooled_verdicts([r for r in decisions if r["scenario"] == sc])
              for sc in dict.fromkeys(r["scenario"] for r in decisions)}
    if args.verdicts_only:
        return verdicts_only(args, work, seeds, decisions, pooled, then)

    ate = []
    for sc in ("convoy", "crossing"):
        for seed in ate_seeds:
            seq, _ = sequence(args.cache, sc, args.frames, seed, size)
            for mode in MODES:
                out = work / f"ate_{sc}_s{seed}_{mode}"
                row = {"sequence": f"synth {sc} seed {seed}", **run(seq, out, mode, "oracle")}
                ate.append(row)
                print(f"{row['sequence']:22s} {mode:7s} ATE {row['ate_m']:.4f} m  lost {row['lost']}", flush=True)
    data = data_dir(required=False)
    if data and args.kitti:
        kitti = Path(data) / "kitti_odometry" / "dataset" / "sequences"
        variants = [int(v) for v in args.kitti_variants.split(",") if v]
        for name in args.kitti.split(","):
            for mode in MODES:
                rows = []
                for nf in variants:
                    out = work / f"kitti{name}_{mode}_nf{nf}"
                    r = run(kitti / name, out, mode, None, **{"slam.n_features": nf})
                    rows.append({"n_features": nf, **r})
                    print(f"KITTI {name:3s} {mode:7s} n_features {nf}: ATE {r['ate_m']:.4f} m  lost {r['lost']}",
                          flush=True)
                first = work / f"kitti{name}_{mode}_nf{variants[0]}"
                row = {"sequence": f"KITTI {name}", **rows[0], "ate_m": round(_median([r["ate_m"] for r in rows]), 4),
                       "ate_m_default": rows[0]["ate_m"], "variants": rows}
                if mode == "moving":
                    row["decisions"] = _kitti_decisions(first)
                    row["replay"] = replay_cost(kitti / name, first, None)
                    print(f"KITTI {name} motion test alone: {row['replay']}", flush=True)
                ate.append(row)
                print(f"{row['sequence']:22s} {mode:7s} ATE median {row['ate_m']:.4f} m (default settings "
                      f"{row['ate_m_default']:.4f})", flush=True)

    raw = None
    if data and args.raw:
        drive = Path(data) / "kitti_raw" / "2011_09_26" / "2011_09_26_drive_0001_sync"
        raw = raw_drive(drive, work, DOCS if args.overlays else None)
        print(f"KITTI raw 0001 (no poses): decisions per label {raw['decisions']}; overlays {raw['overlays']}",
              flush=True)

    # ------------------------------------------------------------------ summary
    table = {}
    for r in ate:
        table.setdefault(r["sequence"], {})[r["mode"]] = r["ate_m"]
    ratios = {s: {"all_over_none": round(v["all"] / v["none"], 3), "moving_over_none": round(v["moving"] / v["none"], 3)}
              for s, v in table.items() if {"none", "all", "moving"} <= set(v)}
    default = {}  # KITTI: the default settings' own runs (the table has the medians over the variants)
    for r in ate:
        if "ate_m_default" in r:
            default.setdefault(r["sequence"], {})[r["mode"]] = r["ate_m_default"]
    for s, v in default.items():
        if {"none", "moving"} <= set(v):
            ratios[s]["moving_over_none_default_run"] = round(v["moving"] / v["none"], 3)
    acc_mixed = pooled.get("mixed", {}).get("rate")
    # the cost target is judged on the test alone (replays), the in-pipeline medians reported beside
    replays = [r["replay"] for r in decisions + ate if "replay" in r]
    ms = _median([r["total_ms"]["median"] for r in replays])
    ms_worst = max((r["total_ms"]["median"] for r in replays), default=None)
    flow_ms = _median([r["motion_flow_ms"]["median"] for r in replays])
    test_ms = _median([r["motion_ms"]["median"] for r in replays])
    pipe_ms = _median([r.get("total_ms") for r in decisions + ate])
    kitti_ok = [v["moving_over_none"] <= TARGET_KITTI_RATIO for s, v in ratios.items() if s.startswith("KITTI")]
    synth_ok = [v["moving_over_none"] <= TARGET_SYNTH_RATIO for s, v in ratios.items() if s.startswith("synth")]
    targets = {
        "mixed_accuracy": {"value": acc_mixed, "target": TARGET_ACCURACY,
                           "met": acc_mixed is not None and acc_mixed >= TARGET_ACCURACY},
        "kitti_moving_over_none": {"target": TARGET_KITTI_RATIO, "met": bool(kitti_ok) and all(kitti_ok)},
        "synth_moving_over_none": {"target": round(TARGET_SYNTH_RATIO, 4), "met": bool(synth_ok) and all(synth_ok)},
        "ms_per_frame": {"value": ms_worst, "target": TARGET_MS, "met": ms_worst is not None and ms_worst <= TARGET_MS},
    }
    print_verdicts(pooled, raw)
    print("\nATE (m): masking none / all (thesis) / moving (default); KITTI: medians over the n_features variants")
    for s, v in table.items():
        r = ratios.get(s, {})
        print(f"{s:22s} {v.get('none', float('nan')):.4f} {v.get('all', float('nan')):.4f} "
              f"{v.get('moving', float('nan')):.4f}   moving/none {r.get('moving_over_none')}  all/none "
              f"{r.get('all_over_none')}"
              + (f"  (default run alone: moving/none {r['moving_over_none_default_run']})"
                 if "moving_over_none_default_run" in r else ""))
    print("\nmotion test alone (replayed), ms per frame, median:")
    for r in decisions + ate:
        if "replay" in r:
            rp = r["replay"]
            print(f"  {r.get('sequence') or r['scenario']:22s} flow {rp['motion_flow_ms']['median']:6.3f}  test "
                  f"{rp['motion_ms']['median']:6.3f}  total {rp['total_ms']['median']:6.3f} (p90 {rp['total_ms']['p90']})"
                  f"  objects/frame {rp['objects_median']:.0f}")
    print(f"in the pipeline (masking thread beside the SLAM on shared cores): {pipe_ms} ms per frame (median)")
    for k, t in targets.items():
        print(f"target {k}: {'met' if t['met'] else 'NOT met'} ({t})")
    result = {
        "benchmark": "moving",
        "machine": machine(),
        "config": {"motion": vars(Config().motion), "frames": args.frames, "size": args.size, "seeds": seeds,
                   "ate_seeds": ate_seeds, "tuned_on_seed": 0, "kitti_n_features": args.kitti_variants},
        "decisions": decisions,
        "decisions_pooled": pooled,
        "ate": ate,
        "ate_table": table,
        "ratios": ratios,
        "kitti_raw_0001": raw,
        "ms": {"replay_motion_flow": flow_ms, "replay_motion": test_ms, "replay_total": ms,
               "replay_total_worst_sequence": ms_worst, "in_pipeline_total": pipe_ms},
        "targets": targets,
    }
    write_json(args.out, result, default=float)
    print(f"-> {args.out}")
    return 0


# the child of --old-commit: one default run with oracle boxes of the tree on PYTHONPATH
OLD_CHILD = (
    "import sys, json, time\n"
    "from dynastereo.api import run_sequence\n"
    "from dynastereo.config import Config\n"
    "cfg = Config().with_overrides({'detector.name': 'oracle'})\n"
    "t = time.perf_counter()\n"
    "res = run_sequence(sys.argv[1], sys.argv[2], cfg, stereo_check=False)\n"
    "print(json.dumps({'wall_s': round(time.perf_counter() - t, 2), 'lost': len(res.lost)}))\n"
)


# the child of --gt-poses: the masker and the motion test of the tree on PYTHONPATH with the
# ground-truth poses (no SLAM), objects.jsonl's box / track / moving written
REPLAY_CHILD = (
    "import sys, json, time\n"
    "from pathlib import Path\n"
    "from dynastereo.config import Config\n"
    "from dynastereo.eval.trajectory import read_trajectory\n"
    "from dynastereo.io import open_sequence\n"
    "from dynastereo.masking import build_masker\n"
    "try:\n"
    "    from dynastereo.objects.motion import MotionJudge, SceneFlow\n"
    "except ImportError:  # a tree from before the objects package\n"
    "    from dynastereo.masking.motion import MotionJudge, SceneFlow\n"
    "seq_dir, out = Path(sys.argv[1]), Path(sys.argv[2])\n"
    "cfg = Config().with_overrides({'detector.name': 'oracle'})\n"
    "seq = open_sequence(seq_dir)\n"
    "masker = build_masker(cfg, seq.calibration, models_dir=None, ground_truth=seq_dir)\n"
    "poses = read_trajectory(seq_dir.parent.parent / 'poses' / (seq_dir.name + '.txt')).poses\n"
    "flow, judge = SceneFlow(cfg.motion), MotionJudge(cfg.motion, seq.calibration)\n"
    "t = time.perf_counter()\n"
    "lines = []\n"
    "for i in range(min(len(seq), len(poses))):\n"
    "    f = seq.frame(i)\n"
    "    m = masker.mask(f)\n"
    "    m.flow = flow.measure(f, m)\n"
    "    judge.select(m)\n"
    "    judge.update(m, poses[i][:3], ok=True)\n"
    "    lines.append(json.dumps({'frame': i, 'objects': [{'box': [float(v) for v in o.box], 'track': int(o.track_id),\n"
    "                                                      'moving': o.moving} for o in m.objects]}))\n"
    "out.mkdir(parents=True, exist_ok=True)\n"
    "(out / 'objects.jsonl').write_text('\\n'.join(lines) + '\\n')\n"
    "print(json.dumps({'wall_s': round(time.perf_counter() - t, 2), 'lost': 0}))\n"
)
THIS_SRC = ROOT / "src"


def run_tree(src: Path, seq: Path, out: Path, gt_poses: bool = False) -> dict:
    """One run of the tree ``src`` (its own process): the default pipeline with oracle boxes,
    like :func:`run`'s ``moving``, or with ``gt_poses`` the replay without SLAM."""
    p = subprocess.run([sys.executable, "-c", REPLAY_CHILD if gt_poses else OLD_CHILD, str(seq), str(out)],
                       env=dict(os.environ, PYTHONPATH=str(src)), capture_output=True, text=True)
    if p.returncode != 0:
        raise RuntimeError(f"{src} on {seq}: exit {p.returncode}\n{p.stderr[-2000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def print_verdicts(pooled: dict, raw: dict | None) -> None:
    """The verdict rates: each scenario's pooled over its seeds, and raw 0001's beside."""
    print("\nverdicts, oracle boxes: ground-truth object-frames >= 300 px after their first 3 frames, "
          "right = matched (IoU >= 0.5) and moving as the ground truth (pooled over the seeds)")
    print(f"{'scenario':10s} {'rate':>6s} {'seed min':>9s} {'seed med':>9s} {'undecided':>10s} {'unmatched':>10s} "
          f"{'mov->stat':>10s} {'stat->mov':>10s} {'object-frames':>14s}")
    for sc, p in pooled.items():
        print(f"{sc:10s} {p['rate']:6.3f} {p['seed_min']:9.3f} {p['seed_median']:9.3f} {p['undecided']:10d} "
              f"{p['unmatched']:10d} {p['moving_judged_static']:10d} {p['static_judged_moving']:10d} "
              f"{p['object_frames']:14d}")
    v = (raw or {}).get("verdicts")
    if v:
        print(f"KITTI raw 0001 (default detector, reference labels): {v['right_of_decided']:.3f} right of the "
              f"{v['right'] + v['wrong']} decided object-frames, {v['undecided']} undecided of {v['object_frames']}")


def verdicts_only(args, work: Path, seeds: list[int], decisions: list[dict], pooled: dict,
                  then: list[dict]) -> int:
    """``--verdicts-only``: raw 0001's verdicts beside the synthetic ones (and ``then``: an old
    commit's decisions on the same sequences); the JSON."""
    raw = None
    compare = None
    if then:
        compare = {"old_commit": args.old_commit, "new": head_commit(), "decisions_old": then,
                   "pooled_old": {sc: pooled_verdicts([r for r in then if r["scenario"] == sc]) for sc in pooled}}
        print(f"\n{'scenario':10s} {'rate ' + args.old_commit:>14s} {'rate now':>9s}  per seed (old -> now)")
        for sc, p in pooled.items():
            pairs = [(a["accuracy"], b["accuracy"]) for a, b in zip(then, decisions) if a["scenario"] == sc]
            print(f"{sc:10s} {compare['pooled_old'][sc]['rate']:14.3f} {p['rate']:9.3f}  "
                  + ", ".join(f"{a:.3f}->{b:.3f}" for a, b in pairs))
    data = data_dir(required=False)
    if data and args.raw:
        drive = Path(data) / "kitti_raw" / "2011_09_26" / "2011_09_26_drive_0001_sync"
        raw = raw_drive(drive, work, None)
    print_verdicts(pooled, raw)
    mixed = pooled.get("mixed", {}).get("rate")
    result = {
        "benchmark": "motion_verdicts",
        "machine": machine(),
        "config": {"motion": vars(Config().motion), "frames": args.frames, "size": args.size, "seeds": seeds,
                   "tuned_on_seed": 0, "poses": "ground truth (replayed, no SLAM)" if args.gt_poses else "SLAM"},
        "decisions": decisions,
        "decisions_pooled": pooled,
        "kitti_raw_0001": raw,
        "compared": compare,
        "targets": {"mixed_accuracy": {"value": mixed, "target": TARGET_ACCURACY,
                                       "met": mixed is not None and mixed >= TARGET_ACCURACY}},
    }
    write_json(args.out, result, default=float)
    print(f"-> {args.out}")
    return 0


class _Overlays:
    """Observer: the left image with the objects in their verdict's colours at ``frames``."""

    def __init__(self, out: Path, frames: tuple[int, ...]):
        self.out, self.frames = out, set(frames)

    def on_frame(self, ev) -> None:
        import cv2

        from dynastereo.viz.draw import draw_objects

        if ev.position in self.frames and ev.masks is not None:
            img = draw_objects(ev.frame.left, ev.masks.left, ev.masks.objects, ev.masks.labels_left)
            cv2.imwrite(str(self.out / f"motion_raw0001_{ev.position:03d}.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, 80])


def raw_drive(drive: Path, work: Path, overlays: Path | None) -> dict:
    """KITTI raw drive 0001 (moving traffic, no poses): the decisions per label, and
    overlays of a few frames (``overlays``: a folder) to check by eye."""
    obs = ()
    if overlays is not None:
        overlays.mkdir(parents=True, exist_ok=True)
        obs = (_Overlays(overlays, RAW_OVERLAY_FRAMES),)
    out = work / "raw0001_moving"
    res = run_sequence(drive, out, Config(), stereo_check=False, observers=obs, overwrite=True)
    return {"frames": len(res.frames), "lost": len(res.lost), "decisions": _kitti_decisions(out),
            "verdicts": score_raw_labels(out) if RAW_LABELS.is_file() else None,
            "overlays": sorted(str(p) for p in overlays.glob("motion_raw0001_*.jpg")) if overlays else [],
            **motion_ms(out)}


def _kitti_decisions(run_dir: Path) -> dict:
    """Per label: object-frames judged moving / static / undecided (no ground truth)."""
    out: dict[str, dict[str, int]] = {}
    for line in (run_dir / "objects.jsonl").read_text().splitlines():
        for o in json.loads(line)["objects"]:
            key = {True: "moving", False: "static", None: "undecided"}[o["moving"]]
            d = out.setdefault(o["label"], {"moving": 0, "static": 0, "undecided": 0})
            d[key] += 1
    return out


if __name__ == "__main__":
    raise SystemExit(main())
