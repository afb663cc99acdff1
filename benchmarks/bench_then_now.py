"""As accurate as before? This checkout's SLAM against an older source tree's, paired.

The SLAM's hot loops were rewritten as compiled kernels; the aim was a SLAM "as accurate
as today" (the code before them, commit 45948c1).  A 51-108-frame clip's ATE moves by a
fifth with changes that should not matter (``slam.n_features`` 2000 vs 2050), so four
variants' medians -- what ``bench_objects.py`` and ``bench_moving.py`` take -- differ by
more than a core that shifts nothing would.  This benchmark compares the two codes
**paired**: the same clip and ``slam.n_features`` variant (``--variants``, default twelve:
1900-2175 in steps of 25), ``--masker none`` (the SLAM alone: masking changed too since
then; ``--masker outline``: the default pipeline, e.g. against the previous commit), each
run in its own process with ``PYTHONPATH`` set to the tree's ``src``, the old and the new
alternated per variant.  Per clip: the ATE (APE RMSE after SE(3) alignment,
against the ground truth ``dynastereo`` finds: KITTI ``poses/NN.txt``, raw drives' OXTS)
and the end-point drift of every run, their medians and means, the per-variant
differences new - old (median, and in how many variants the new code is the more
accurate), and the frames lost.

The old tree is ``git archive OLD src`` of this repository (``--old-commit``, default
45948c1) unpacked into a temporary folder, or a source folder (``--old-src``).  Both run
with this checkout's virtual environment.  Writes benchmarks/results/then_now.json.

    DYNASTEREO_DATA=/work/shared/data DYNASTEREO_MODELS=/work/shared/models \\
        .venv/bin/python benchmarks/bench_then_now.py [--clips raw0001,06,03] [--variants 2000,1950] \\
        [--old-commit 45948c1] [--masker none|outline] [--mask-all] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from _common import CLIPS, ROOT, data_dir, machine, now, results_path, write_json
from _shared_runs import head_commit as _head
from _shared_runs import old_tree

OUT = results_path("then_now")
VARIANTS = tuple(range(1900, 2176, 25))
# the child: one run of the tree on PYTHONPATH (its own process: nothing shared between codes)
CHILD = (
    "import sys, json, time\n"
    "from dynastereo.api import run_sequence\n"
    "from dynastereo.config import Config\n"
    "seq, out, nf, masker, mode = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4], sys.argv[5]\n"
    "over = {'masker.kind': masker, 'slam.n_features': nf}\n"
    "if mode != 'moving':  # the default, left out: a tree from before the motion test has no such key\n"
    "    over['motion.mode'] = mode\n"
    "cfg = Config().with_overrides(over)\n"
    "t = time.perf_counter()\n"
    "res = run_sequence(seq, out, cfg)\n"
    "print(json.dumps({'wall_s': time.perf_counter() - t, 'lost': len(res.lost)}))\n"
)


def run_one(src: Path, seq: Path, out: Path, nf: int, masker: str, mode: str) -> dict:
    env = dict(os.environ, PYTHONPATH=str(src))
    shutil.rmtree(out, ignore_errors=True)  # this benchmark's own folder: the API refuses to overwrite by default
    p = subprocess.run([sys.executable, "-c", CHILD, str(seq), str(out), str(nf), masker, mode], env=env,
                       capture_output=True, text=True)
    if p.returncode != 0:
        raise RuntimeError(f"{src} on {seq.name}, n_features {nf}: exit {p.returncode}\n{p.stderr[-2000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def accuracy(run_dir: Path, gt: Path) -> dict:
    from dynastereo.eval import evaluate_files

    ev = evaluate_files(run_dir / "trajectory.kitti.txt", gt)
    return {"ate_m": round(float(ev.ape["rmse"]), 5), "drift_percent": round(float(ev.drift_percent), 4)}


def summary(rows: list[dict]) -> dict:
    """Per clip: medians / means of both codes and the paired differences new - old."""
    new = np.array([r["new"]["ate_m"] for r in rows])
    old = np.array([r["old"]["ate_m"] for r in rows])
    d = new - old
    dn = np.array([r["new"]["drift_percent"] for r in rows])
    do = np.array([r["old"]["drift_percent"] for r in rows])
    return {
        "variants": len(rows),
        "ate_median_new": float(np.median(new)), "ate_median_old": float(np.median(old)),
        "ate_mean_new": float(new.mean()), "ate_mean_old": float(old.mean()),
        "ate_range_new": [float(new.min()), float(new.max())], "ate_range_old": [float(old.min()), float(old.max())],
        "ate_ratio_of_medians": float(np.median(new) / np.median(old)),
        "ate_ratio_of_means": float(new.mean() / old.mean()),
        "paired_difference_median_m": float(np.median(d)),
        "new_more_accurate": int((d < 0).sum()), "old_more_accurate": int((d > 0).sum()),
        "drift_median_new": float(np.median(dn)), "drift_median_old": float(np.median(do)),
        "lost_new": int(sum(r["new"]["lost"] for r in rows)), "lost_old": int(sum(r["old"]["lost"] for r in rows)),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clips", default="raw0001,06,03")
    ap.add_argument("--variants", default=",".join(map(str, VARIANTS)), help="slam.n_features per pair of runs")
    ap.add_argument("--old-commit", default="45948c1", help="the code before the compiled core")
    ap.add_argument("--old-src", type=Path, default=None, help="an old source folder instead of --old-commit")
    ap.add_argument("--masker", default="none", help="masker.kind of every run: none (the SLAM alone) | outline")
    ap.add_argument("--mask-all", action="store_true", help="motion.mode all: every detection masked (no verdicts)")
    ap.add_argument("--work", type=Path, default=None, help="run folders (default: a new temporary folder)")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    data = data_dir()
    from dynastereo.eval.trajectory import find_ground_truth

    work = args.work or Path(tempfile.mkdtemp(prefix="bench_then_now_"))
    old_src = args.old_src or old_tree(args.old_commit, work / "old")
    new_src = ROOT / "src"
    variants = [int(v) for v in args.variants.split(",") if v]
    mode = "all" if args.mask_all else "moving"
    result = {"benchmark": "then_now", "date": now(),
              "old": args.old_commit if args.old_src is None else str(args.old_src),
              "new": _head(),
              "machine": machine(),
              "masker": args.masker, "motion_mode": mode, "variants": variants, "clips": {}}
    for clip in [c for c in args.clips.split(",") if c]:
        seq = data / CLIPS[clip]
        gt = find_ground_truth(seq)
        if gt is None:
            print(f"{clip}: no ground truth next to {seq}: skipped", flush=True)
            continue
        rows = []
        for nf in variants:
            row = {"n_features": nf}
            for side, src in (("old", old_src), ("new", new_src)):
                out = work / f"{clip}_{side}_{nf}"
                r = run_one(src, seq, out, nf, args.masker, mode)
                row[side] = {**accuracy(out, gt), "lost": r["lost"], "wall_s": round(r["wall_s"], 2)}
            rows.append(row)
            print(f"{clip} n_features {nf}: ATE old {row['old']['ate_m']:.4f}  new {row['new']['ate_m']:.4f} m",
                  flush=True)
        s = summary(rows)
        result["clips"][clip] = {"runs": rows, "summary": s}
    print(f"\n--masker {args.masker}, motion.mode {mode}, {len(variants)} slam.n_features variants, old = {result['old']}, new = {result['new']}")
    print(f"{'clip':8s} {'ATE median old':>15s} {'new':>7s} {'mean old':>9s} {'new':>7s} {'paired new-old':>15s} "
          f"{'new better':>11s} {'drift old':>10s} {'new':>6s} {'lost':>6s}")
    for clip, c in result["clips"].items():
        s = c["summary"]
        print(f"{clip:8s} {s['ate_median_old']:15.4f} {s['ate_median_new']:7.4f} {s['ate_mean_old']:9.4f} "
              f"{s['ate_mean_new']:7.4f} {s['paired_difference_median_m']:+15.4f} "
              f"{s['new_more_accurate']:>5d} of {s['variants']:<3d} {s['drift_median_old']:9.3f}% "
              f"{s['drift_median_new']:5.3f}% {s['lost_old']:>3d}/{s['lost_new']}")
    write_json(args.out, result)
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
