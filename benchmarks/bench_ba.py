"""Benchmark the local bundle adjustment: the compiled kernel against gtsam, same problems.

The problems are captured from a ``dynastereo.api.run_sequence`` of KITTI 06 (51 frames,
the default pipeline): every BA the run submits (``local_mapping.run_ba``).  That run has
10 local BAs and 4 self-calibrating ones; each self-calibrating BA is three solves (the
disparity offsets -0.3, 0, +0.3 px), taken as separate problems: the first ``--problems``
(default 20) of those solves, local ones first.

Each problem is solved by

* **gtsam** (``optimizer.local_ba_gtsam``, the solver before the kernel) with that code's
  settings: 3 robust LM iterations (``slam.ba_iterations`` was 3), ``rel_tol`` 1e-3;
* **the kernel, same settings** (``optimizer.local_ba``: 3 robust iterations, no refine
  stage): final costs side by side (the Huber cost over all observations, gtsam's
  ``graph.error``);
* **the kernel, today's defaults** (ORB-SLAM2's schedule: 5 robust iterations, outliers
  dropped, 10 without the kernel; self-calibrating solves robust only, as the run does).

Time: wall ms and CPU ms (``time.process_time``: all threads of the process) per problem,
the fastest of ``--repeats`` (default 3) solves, the solvers alternated.  The kernel is
compiled / loaded from cache before timing (its first-call times are reported apart).
Target: kernel CPU <= 1/4 of gtsam's, medians over the problems.

Prints medians; writes benchmarks/results/ba.json.  Run:

    DYNASTEREO_DATA=/work/shared/data DYNASTEREO_MODELS=/work/shared/models \\
        .venv/bin/python benchmarks/bench_ba.py [--problems 20] [--repeats 3] [--save PKL | --load PKL]

``--ate OLD_SRC`` instead measures accuracy, this code against another checkout's
``src`` (e.g. the code before the kernel): ``run_sequence`` of KITTI 06 (default
pipeline) and 03 (``masker.kind: none``) at ``slam.n_features`` 2000 / 1950 / 2050 / 2100
(as ``bench_moving.py`` takes them), each in its own process, the two codes alternated;
ATE medians over the four and their ratio (target <= 1.10); writes
benchmarks/results/ba_ate.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pickle
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import ROOT, data_path, machine, median, results_path, write_json

OUT = results_path("ba")
TARGET_CPU_RATIO = 0.25


def capture(seq: Path) -> list:
    """Every BA problem a default run of ``seq`` submits."""
    import dynastereo.slam.local_mapping as lm
    from dynastereo.api import run_sequence
    from dynastereo.config import Config

    probs = []
    orig = lm.run_ba

    def cap(p, abort=None):
        probs.append(dataclasses.replace(p))
        return orig(p, abort)

    lm.run_ba = cap
    try:
        with tempfile.TemporaryDirectory() as tmp:
            run_sequence(seq, Path(tmp) / "run", Config(), stereo_check=False, overwrite=True)
    finally:
        lm.run_ba = orig
    return probs


def expand(probs: list, n: int) -> list[tuple[str, object]]:
    """Local problems first, then the self-calibrating BAs' solves (one per offset)."""
    from dynastereo.slam.optimizer import shift_disparity

    local = [("local", p) for p in probs if not p.offset_grid]
    selfcal = []
    for p in probs:
        if p.offset_grid:
            for d in p.offset_grid:
                selfcal.append(("selfcal", dataclasses.replace(
                    p, ur=shift_disparity(p.uv[:, 0], p.ur, float(d)), offset_grid=None)))
    return (local + selfcal)[:n]


def timed(fn, p, repeats: int):
    best = None
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        r = fn(p)
        w, c = (time.perf_counter() - w0) * 1e3, (time.process_time() - c0) * 1e3
        if best is None or c < best[2]:
            best = (r, w, c)
    return best


ATE_SNIPPET = """
import json, sys
from pathlib import Path
import dynastereo
from dynastereo.api import run_sequence
from dynastereo.config import Config
from dynastereo.eval import evaluate_files
seq, masker, nf, out = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3]), Path(sys.argv[4])
over = {"slam.n_features": nf}
if masker == "none":
    over["masker.kind"] = "none"
res = run_sequence(seq, out, Config().with_overrides(over), stereo_check=False, overwrite=True)
ev = evaluate_files(out / "trajectory.kitti.txt", seq.parent.parent / "poses" / f"{seq.name}.txt")
st = json.loads((out / "run.json").read_text())["stats"]
print(json.dumps({"ate_m": round(float(ev.ape["rmse"]), 4), "lost": len(res.lost), "local_ba_runs": st["local_ba_runs"],
                  "local_ba_ms_median": round(st["local_ba_ms_median"], 1)}))
"""
VARIANTS = (2000, 1950, 2050, 2100)


def ate(old_src: str, out_path: Path) -> int:
    import subprocess

    data = data_path("kitti_odometry", "dataset", "sequences")
    new_src = str(ROOT / "src")
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for nf in VARIANTS:
            for seq, masker in (("06", "default"), ("03", "none")):
                for code, src in (("old", old_src), ("kernel", new_src)):
                    env = dict(os.environ, PYTHONPATH=src)
                    out = Path(tmp) / f"{code}_{seq}_{nf}"
                    r = subprocess.run([sys.executable, "-c", ATE_SNIPPET, str(data / seq), masker, str(nf), str(out)],
                                       env=env, capture_output=True, text=True)
                    if r.returncode:
                        print(r.stderr[-2000:], file=sys.stderr)
                        return 1
                    row = {"code": code, "seq": seq, "masker": masker, "n_features": nf,
                           **json.loads(r.stdout.strip().splitlines()[-1])}
                    runs.append(row)
                    print(f"{code:6s} KITTI {seq} {masker:7s} n_features {nf}: ATE {row['ate_m']:.4f} m, lost {row['lost']}",
                          flush=True)
    med = {f"{c}_{s}": _median([r["ate_m"] for r in runs if r["code"] == c and r["seq"] == s])
           for c in ("old", "kernel") for s in ("06", "03")}
    res = {"runs": runs, "medians": med, "ratio_06": round(med["kernel_06"] / med["old_06"], 3),
           "ratio_03": round(med["kernel_03"] / med["old_03"], 3), "target_ratio": 1.10}
    print(f"ATE medians over n_features {VARIANTS}: 06 old {med['old_06']:.4f} kernel {med['kernel_06']:.4f} "
          f"({res['ratio_06']}x); 03 old {med['old_03']:.4f} kernel {med['kernel_03']:.4f} ({res['ratio_03']}x)")
    write_json(out_path, res)
    print(f"written {out_path}")
    return 0


def _median(v):
    return median(v)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--problems", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--save", help="write the captured problems to this pickle")
    ap.add_argument("--load", help="read the problems from this pickle instead of a run")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--ate", metavar="OLD_SRC", help="measure ATE against the code in OLD_SRC instead (module doc)")
    args = ap.parse_args()
    if args.ate:
        return ate(args.ate, OUT.parent / "ba_ate.json")

    from dynastereo.slam.kernels import ba as ba_kernel
    from dynastereo.slam.optimizer import local_ba, local_ba_gtsam

    t0 = time.perf_counter()
    ba_kernel.warm_up()
    first_call_s = time.perf_counter() - t0
    if args.load:
        probs = pickle.loads(Path(args.load).read_bytes())
    else:
        probs = capture(data_path("kitti_odometry", "dataset", "sequences", "06"))
        if args.save:
            Path(args.save).write_bytes(pickle.dumps(probs))
    items = expand(probs, args.problems)
    print(f"{len(items)} problems from {len(probs)} BAs of a KITTI 06 run; kernel first call (compile or cache load) "
          f"{first_call_s:.2f} s", flush=True)

    rows = []
    for kind, p in items:
        p_old = dataclasses.replace(p, iterations=3, refine_iterations=0, rel_tol=1e-3)  # the code before
        g, gw, gc = timed(local_ba_gtsam, p_old, args.repeats)
        k, kw, kc = timed(local_ba, p_old, args.repeats)
        p_new = p if kind == "local" else dataclasses.replace(p, refine_iterations=0)
        n, nw, nc = timed(local_ba, p_new, args.repeats)
        row = {
            "kind": kind, "keyframes": len(p.kf_ids), "fixed": int(np.sum(p.fixed)), "points": len(p.pt_ids),
            "observations": len(p.obs_kf),
            "cost_before": round(g.error_before, 3),
            "gtsam": {"cost": round(g.error_after, 3), "iterations": g.iterations, "wall_ms": round(gw, 2),
                      "cpu_ms": round(gc, 2)},
            "kernel_same_settings": {"cost": round(k.error_after, 3), "iterations": k.iterations,
                                     "wall_ms": round(kw, 2), "cpu_ms": round(kc, 2),
                                     "max_pose_diff_m": float(np.abs(k.T_wc[:, :3, 3] - g.T_wc[:, :3, 3]).max())},
            "kernel_defaults": {"cost": round(n.error_after, 3), "iterations": n.iterations, "wall_ms": round(nw, 2),
                                "cpu_ms": round(nc, 2),
                                "outliers": int((~n.inlier).sum()) if n.inlier is not None else None},
        }
        rows.append(row)
        print(f"{kind:8s} K {row['keyframes']:2d} P {row['points']:5d} M {row['observations']:6d} | cost "
              f"{row['cost_before']:9.1f} -> gtsam {g.error_after:9.1f} ({g.iterations} it, {gc:7.1f} ms CPU) "
              f"kernel {k.error_after:9.1f} ({k.iterations} it, {kc:6.1f} ms) defaults {n.error_after:9.1f} "
              f"({n.iterations} it, {nc:6.1f} ms)", flush=True)

    def med(solver, key):
        return _median([r[solver][key] for r in rows])

    rel_cost = [r["kernel_same_settings"]["cost"] / r["gtsam"]["cost"] - 1.0 for r in rows]
    summary = {
        "problems": len(rows),
        "gtsam_cpu_ms_median": med("gtsam", "cpu_ms"),
        "gtsam_wall_ms_median": med("gtsam", "wall_ms"),
        "kernel_same_settings_cpu_ms_median": med("kernel_same_settings", "cpu_ms"),
        "kernel_same_settings_wall_ms_median": med("kernel_same_settings", "wall_ms"),
        "kernel_defaults_cpu_ms_median": med("kernel_defaults", "cpu_ms"),
        "kernel_defaults_wall_ms_median": med("kernel_defaults", "wall_ms"),
        "cpu_ratio_same_settings": round(med("kernel_same_settings", "cpu_ms") / med("gtsam", "cpu_ms"), 4),
        "cpu_ratio_defaults": round(med("kernel_defaults", "cpu_ms") / med("gtsam", "cpu_ms"), 4),
        "cpu_ratio_per_problem_median": round(_median([r["kernel_defaults"]["cpu_ms"] / r["gtsam"]["cpu_ms"]
                                                       for r in rows]), 4),
        "cost_rel_diff_same_settings_median": _median(rel_cost),
        "cost_rel_diff_same_settings_max_abs": float(np.max(np.abs(rel_cost))),
        "kernel_first_call_s": round(first_call_s, 2),
    }
    summary["target_cpu_ratio"] = TARGET_CPU_RATIO
    summary["met"] = summary["cpu_ratio_defaults"] <= TARGET_CPU_RATIO
    print("\nmedians over the problems (CPU ms per problem, fastest of "
          f"{args.repeats}): gtsam {summary['gtsam_cpu_ms_median']:.1f}, kernel same settings "
          f"{summary['kernel_same_settings_cpu_ms_median']:.1f} ({summary['cpu_ratio_same_settings']:.3f}x), "
          f"kernel defaults (5+10) {summary['kernel_defaults_cpu_ms_median']:.1f} "
          f"({summary['cpu_ratio_defaults']:.3f}x; target <= {TARGET_CPU_RATIO})")
    print(f"final cost, kernel vs gtsam at the same settings: median relative difference "
          f"{summary['cost_rel_diff_same_settings_median']:+.2e}, largest {summary['cost_rel_diff_same_settings_max_abs']:.2e}")
    out = {"summary": summary, "rows": rows,
           "machine": machine()}
    write_json(args.out, out)
    print(f"written {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
