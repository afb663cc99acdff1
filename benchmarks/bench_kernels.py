"""The SLAM's compiled kernels against the numpy / OpenCV code they replace.

Part 1, side by side in one run (``--masker none`` on each KITTI clip): every call of a
replaced stage runs both versions, in alternating order, on the same input -- the
kernel's result drives the run, the old one is only timed and compared:

* ``stereo``: ``matcher.stereo_match`` (kernel) vs ``matcher._stereo_match_numpy``;
* ``pose``: ``optimizer.optimize_pose`` (kernel) vs ``optimizer._optimize_pose_numpy``;
* ``knn``: ``kernels.hamming.knn_hamming`` vs ``cv2.batchDistance`` (the descriptor
  candidates of ``keyframe_point_matches``);
* ``epipolar``: ``kernels.epipolar.epipolar_best`` (triangulation's candidates in
  ``create_new_points``) vs what local mapping did before it (:func:`epipolar_old`: the 4
  nearest descriptors by ``knn_hamming``, then the line and epipole tests in numpy, the best);
* ``projection``: ``matcher.search_by_projection`` (kernel) vs
  ``matcher._search_by_projection_numpy`` (tracking's last-frame and local-map searches
  and local mapping's fusion).

CPU ms a frame (the calling thread's CPU time, summed over the frame's calls; medians
over the frames after the first, whose calls load the compiled code), the Python-level
calls a frame (counted on frames 1-10 in an extra, untimed call; median per call x calls a frame) and the agreement: identical matches, the largest pose difference.

Part 2, the whole ``dynastereo run --masker none`` (``api.run_sequence``, its own process
each time) with the old code (``--old SRC``: a source tree from before the kernels, e.g.
``git archive 45948c1 src | tar -x -C /tmp/base`` and ``--old /tmp/base/src``; the design
notes' figures were measured so) and this checkout's, alternated, ``--repeats`` times: the frame loop's FPS and the process
tree's CPU a frame over the frame loop (start-up left out), medians; and the trajectories'
largest difference between old and new.

Part 0 (first): numba's compile time on a first run (empty cache), the cached load, and the
import time of the SLAM against the old code's.

    DYNASTEREO_DATA=... .venv/bin/python benchmarks/bench_kernels.py [--sequences 06,03] \\
        [--repeats 3] [--old /tmp/base/src] [--skip-runs] [--skip-compile]

Prints the tables and writes benchmarks/results/kernels.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np

from _common import BENCH, CLIPS, ROOT, data_dir, results_path, write_json

RESULTS = results_path("kernels")


def epipolar_old(d1, uv1, m1, d2, uv2, m2, th2, near2, F21, epipole, max_dist, k_nn=4):
    """Triangulation's candidates as local mapping found them before ``epipolar_best``: the
    ``k_nn`` nearest descriptors of keyframe 2 (``knn_hamming``), within ``max_dist``, on the
    epipolar line, not a monocular pair near the epipole; the nearest left per row."""
    from dynastereo.slam.kernels.hamming import knn_hamming

    best, dist = np.full(len(d1), -1, np.int64), np.full(len(d1), -1, np.int64)
    K = min(k_nn, len(d2))
    if K == 0 or len(d1) == 0:
        return best, dist
    dnn, inn = knn_hamming(d1, d2, K)
    a, b, d = np.repeat(np.arange(len(d1)), K), inn.reshape(-1), dnn.reshape(-1)
    ok = (b >= 0) & (d <= max_dist)
    a, b, d = a[ok], b[ok], d[ok]
    lines = np.c_[uv1[a], np.ones(len(a))] @ F21.T
    num = (lines * np.c_[uv2[b], np.ones(len(b))]).sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ok = num**2 / (lines[:, 0] ** 2 + lines[:, 1] ** 2) < th2[b]
    if epipole is not None:
        near = (uv2[b, 0] - epipole[0]) ** 2 + (uv2[b, 1] - epipole[1]) ** 2 < near2[b]
        ok &= ~(m1[a] & m2[b] & near)
    a, b, d = a[ok], b[ok], d[ok]
    first = np.unique(a, return_index=True)[1]  # the nearest first within each row
    best[a[first]], dist[a[first]] = b[first], d[first]
    return best, dist


class SideBySide:
    """Wraps the replaced functions; per frame CPU ms of new and old, and mismatches."""

    def __init__(self) -> None:
        self.frame = -1
        self.ms: dict[str, dict[str, defaultdict]] = defaultdict(lambda: {"new": defaultdict(float), "old": defaultdict(float)})
        self.calls: dict[str, int] = defaultdict(int)
        self.diff: dict[str, list] = defaultdict(list)
        self._flip = False
        self.pycalls: dict[str, dict[str, list]] = defaultdict(lambda: {"new": [], "old": []})

    @staticmethod
    def _count_calls(fn) -> int:
        """Python-level calls (Python functions and C functions called from Python) of ``fn()``."""
        n = 0

        def prof(frame, event, arg):
            nonlocal n
            if event in ("call", "c_call"):
                n += 1

        sys.setprofile(prof)
        try:
            fn()
        finally:
            sys.setprofile(None)
        return n

    def _both(self, stage, new, old):
        """Run ``new`` and ``old`` (alternating which goes first); returns both results.  On
        frames 1-10 both also run once more, untimed, to count their Python-level calls."""
        if 1 <= self.frame <= 10:
            for name, fn in (("new", new), ("old", old)):
                self.pycalls[stage][name].append(self._count_calls(fn))
        self._flip = not self._flip
        order = (("new", new), ("old", old)) if self._flip else (("old", old), ("new", new))
        out = {}
        for name, fn in order:
            t = time.thread_time()
            out[name] = fn()
            self.ms[stage][name][self.frame] += (time.thread_time() - t) * 1e3
        self.calls[stage] += 1
        return out["new"], out["old"]

    def install(self) -> None:
        from dynastereo.slam import local_mapping, loop_closing, matcher, optimizer, tracking

        sbs = self
        new_stereo, old_stereo = matcher.stereo_match, matcher._stereo_match_numpy

        def stereo(*a, **k):
            sbs.frame += 1
            n, o = sbs._both("stereo", lambda: new_stereo(*a, **k), lambda: old_stereo(*a, **k))
            same = np.array_equal(n.u_right, o.u_right) and np.array_equal(n.depth, o.depth)
            sbs.diff["stereo"].append(dict(same=same, matches=int((n.depth > 0).sum()),
                                           differ=int((n.u_right != o.u_right).sum())))
            return n

        tracking.stereo_match = stereo

        new_pose, old_pose = optimizer.optimize_pose, optimizer._optimize_pose_numpy

        def pose(*a, **k):
            (Tn, inn), (To, ino) = sbs._both("pose", lambda: new_pose(*a, **k), lambda: old_pose(*a, **k))
            sbs.diff["pose"].append(dict(dT=float(np.abs(Tn - To).max()), inliers_differ=int((inn != ino).sum()), n=len(inn)))
            return Tn, inn

        tracking.optimize_pose = pose
        loop_closing.optimize_pose = pose

        from dynastereo.slam.kernels import hamming

        def knn(a, b, k):
            (dn, iN), (do, io) = sbs._both(
                "knn", lambda: hamming.knn_hamming(a, b, k),
                lambda: cv2.batchDistance(a, b, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=min(k, len(b))))
            sbs.diff["knn"].append(dict(same=bool(np.array_equal(dn, do) and np.array_equal(iN, io))))
            return dn, iN

        matcher.knn_hamming = knn
        new_epi = local_mapping.epipolar_best

        def epi(*a, **k):
            (bn, dn), (bo, do) = sbs._both("epipolar", lambda: new_epi(*a, **k), lambda: epipolar_old(*a, **k))
            sbs.diff["epipolar"].append(dict(same=bool(np.array_equal(bn, bo) and np.array_equal(dn, do)),
                                             matches=int((bn >= 0).sum())))
            return bn, dn

        local_mapping.epipolar_best = epi

        if hasattr(matcher, "_search_by_projection_numpy"):
            new_sp, old_sp = matcher.search_by_projection, matcher._search_by_projection_numpy

            def sp(*a, **k):
                n, o = sbs._both("projection", lambda: new_sp(*a, **k), lambda: old_sp(*a, **k))
                same = all(np.array_equal(getattr(n, f), getattr(o, f)) for f in ("query", "kp", "dist"))
                sbs.diff["projection"].append(dict(same=same, matches=len(n.query)))
                return n

            for mod in (tracking, local_mapping, loop_closing):
                mod.search_by_projection = sp

    def summary(self, n_frames: int) -> dict:
        out = {}
        for stage, d in self.ms.items():
            row = {}
            for ver in ("new", "old"):
                per = np.zeros(n_frames)
                for f, v in d[ver].items():
                    if 0 <= f < n_frames:
                        per[f] += v
                row[f"{ver}_ms_median"] = round(float(np.median(per[1:])), 3)
                row[f"{ver}_ms_mean"] = round(float(per[1:].mean()), 3)
                row[f"{ver}_ms_first_frame"] = round(float(per[0]), 3)
            row["speedup_mean"] = round(row["old_ms_mean"] / max(row["new_ms_mean"], 1e-9), 1)
            row["calls_per_frame"] = round(self.calls[stage] / n_frames, 2)
            for ver in ("new", "old"):
                c = self.pycalls[stage][ver]
                # median over the calls: a kernel's first call also runs numba's (Python) cache loader
                row[f"{ver}_py_calls_per_frame"] = round(float(np.median(c)) * row["calls_per_frame"]) if c else None
            diffs = self.diff[stage]
            if stage == "pose":
                row["max_pose_diff"] = float(max((x["dT"] for x in diffs), default=0.0))
                row["calls_inliers_differ"] = sum(x["inliers_differ"] > 0 for x in diffs)
            else:
                row["calls_identical"] = sum(bool(x["same"]) for x in diffs)
            row["calls"] = len(diffs)
            out[stage] = row
        return out


def side_by_side(seq: Path) -> dict:
    from dynastereo.api import run_sequence
    from dynastereo.config import Config

    cfg = Config().with_overrides({"masker.kind": "none"})
    warm_all()  # every kernel loaded before the timed calls (a kernel first called after frame 0 would pay it)
    sbs = SideBySide()
    sbs.install()
    with tempfile.TemporaryDirectory() as tmp:
        res = run_sequence(seq, Path(tmp) / "run", cfg, overwrite=True)
    n = sbs.frame + 1
    return {"frames": n, "lost": len(res.lost), "stages": sbs.summary(n)}


DRIVER = r"""
import json, sys, tempfile
from pathlib import Path
from _shared_cpu import LoopCpu
from dynastereo.api import run_sequence
from dynastereo.config import Config
cfg = Config().with_overrides({"masker.kind": "none"})
loop = LoopCpu()
out = Path(sys.argv[2])
run_sequence(Path(sys.argv[1]), out, cfg, observers=(loop,))
t = json.loads((out / "timing.json").read_text())
print(json.dumps({"fps": t["summary"]["fps"], "cpu_ms": loop.ms_per_frame}))
"""


def whole_run(seq: Path, src: Path, out: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join((str(src), str(BENCH))))  # _shared_cpu from benchmarks/
    r = subprocess.run([sys.executable, "-c", DRIVER, str(seq), str(out)],
                       env=env, capture_output=True, text=True, check=True)
    d = json.loads(r.stdout.strip().splitlines()[-1])
    d["traj"] = np.loadtxt(out / "trajectory.kitti.txt").reshape(-1, 3, 4)
    return d


def warm_all() -> None:
    """One small call of every kernel, with the argument types of a real run."""
    from dynastereo.slam.warmup import warm_up_kernels

    warm_up_kernels(ba=False)


def compile_times(old_src: Path) -> dict:
    """numba, each in a fresh process: the SLAM's import (numba's included; the old code's
    beside it), then the first call of every kernel with an empty cache (compile) and with
    the cache filled (load)."""
    code = ("import sys, time; t0=time.perf_counter(); import dynastereo.slam.tracking, dynastereo.slam.local_mapping; "
            "t1=time.perf_counter(); "
            "t2=time.perf_counter(); c2=time.process_time(); "
            "from dynastereo.slam.warmup import warm_up_kernels; warm_up_kernels(ba=False); "  # as warm_all()
            "print(t1-t0, time.perf_counter()-t2, time.process_time()-c2)")

    def once(env):
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True, cwd=ROOT)
        return [float(x) for x in out.stdout.split()[-3:]]

    with tempfile.TemporaryDirectory() as d:
        env = dict(os.environ, NUMBA_CACHE_DIR=d, PYTHONPATH=str(ROOT / "src"))
        imp1, first, first_cpu = once(env)
        imp2, cached, cached_cpu = once(env)
    old_code = "import time; t0=time.perf_counter(); import dynastereo.slam.tracking, dynastereo.slam.local_mapping; print(time.perf_counter()-t0)"
    old_imp = float(subprocess.run([sys.executable, "-c", old_code], env=dict(os.environ, PYTHONPATH=str(old_src)),
                                   capture_output=True, text=True, check=True).stdout.split()[-1])
    return {"first_call_compile_s": round(first, 2), "first_call_cached_s": round(cached, 2),
            "first_call_compile_cpu_s": round(first_cpu, 2), "first_call_cached_cpu_s": round(cached_cpu, 2),
            "import_s": round(min(imp1, imp2), 2), "import_old_s": round(old_imp, 2)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sequences", default="06,03")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--old", default="/work/main/src")
    ap.add_argument("--skip-runs", action="store_true", help="only the side-by-side stages")
    ap.add_argument("--skip-compile", action="store_true")
    args = ap.parse_args()
    data = data_dir()
    # parts skipped this time keep their figures from the last full run
    old = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    res: dict = {"sequences": {}}
    if args.skip_compile and "numba" in old:
        res["numba"] = old["numba"]
    if not args.skip_compile:
        res["numba"] = c = compile_times(Path(args.old))
        print(f"numba: the kernels' first calls {c['first_call_compile_s']} s ({c['first_call_compile_cpu_s']} s CPU) with an "
              f"empty cache (compile), {c['first_call_cached_s']} s ({c['first_call_cached_cpu_s']} s CPU) from the cache; the SLAM's import {c['import_s']} s (old code {c['import_old_s']} s)")
    for name in filter(None, args.sequences.split(",")):
        seq = data / CLIPS[name]
        r = {"side_by_side": side_by_side(seq)}
        print(f"KITTI {name}: {r['side_by_side']['frames']} frames, CPU ms a frame (median / mean), new vs old, same run")
        for st, row in r["side_by_side"]["stages"].items():
            agree = (f"max pose diff {row['max_pose_diff']:.1e}, {row['calls_inliers_differ']} calls with other inliers"
                     if st == "pose" else f"{row['calls_identical']}/{row['calls']} calls identical")
            print(f"  {st:11s} {row['new_ms_median']:7.2f} / {row['new_ms_mean']:7.2f}  vs {row['old_ms_median']:7.2f} / "
                  f"{row['old_ms_mean']:7.2f}  (x{row['speedup_mean']}, {row['calls_per_frame']} calls a frame; Python calls a "
                  f"frame {row['new_py_calls_per_frame']} vs {row['old_py_calls_per_frame']}; {agree})")
        if not args.skip_runs:
            runs: dict[str, list] = {"old": [], "new": []}
            with tempfile.TemporaryDirectory() as tmp:
                for k in range(args.repeats):
                    for ver, src in (("old", Path(args.old)), ("new", ROOT / "src")):
                        runs[ver].append(whole_run(seq, src, Path(tmp) / f"{ver}{k}"))
            whole = {}
            for ver, rs in runs.items():
                whole[ver] = {"fps": round(float(np.median([x["fps"] for x in rs])), 2),
                              "cpu_ms_per_frame": round(float(np.median([x["cpu_ms"] for x in rs])), 1),
                              "fps_runs": [x["fps"] for x in rs], "cpu_runs": [round(x["cpu_ms"], 1) for x in rs]}
            dt = [float(np.abs(a["traj"][:, :, 3] - b["traj"][:, :, 3]).max()) for a in runs["new"] for b in runs["old"]]
            same_new = all(np.array_equal(runs["new"][0]["traj"], x["traj"]) for x in runs["new"][1:])
            whole["max_position_diff_new_vs_old_m"] = round(max(dt), 6)
            whole["max_pose_entry_diff_new_vs_old"] = max(float(np.abs(a["traj"] - b["traj"]).max())
                                                          for a in runs["new"] for b in runs["old"])
            whole["new_runs_identical"] = bool(same_new)
            r["whole_run"] = whole
            print(f"  dynastereo run --masker none: old {whole['old']['fps']} FPS, {whole['old']['cpu_ms_per_frame']} ms CPU a frame; "
                  f"new {whole['new']['fps']} FPS, {whole['new']['cpu_ms_per_frame']} ms; trajectories differ by at most "
                  f"{whole['max_position_diff_new_vs_old_m']} m; new runs identical: {same_new}")
        elif "whole_run" in old.get("sequences", {}).get(name, {}):
            r["whole_run"] = old["sequences"][name]["whole_run"]
        res["sequences"][name] = r
    write_json(RESULTS, res)
    print(f"-> {RESULTS}")


if __name__ == "__main__":
    main()
