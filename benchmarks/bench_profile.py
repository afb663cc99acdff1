"""Where the CPU goes in one ``dynastereo run``: wall and CPU time per thread and process,
beside what its parts cost alone -- the CPU budget of the real-time design.

Runs ``api.run_sequence`` on a KITTI sequence with the default settings (the way a user
runs it: images read and masked on the prefetch thread, tracking on the main thread, the
local BA in its worker process), then reads from ``/proc`` the CPU time (user + system)
of every thread of this process (by its name: ``MainThread`` is the tracking,
``prefetch`` the reading and masking of the next frame, ``features`` the right image's ORB
beside the left one's; OpenCV / onnxruntime pools show as native threads) and from ``getrusage`` that of the child processes (the BA
workers), beside the run's per-stage medians from ``timing.json``.  The share of the two
cores used is total CPU / (wall x cores).

    DYNASTEREO_DATA=... DYNASTEREO_MODELS=... .venv/bin/python benchmarks/bench_profile.py \\
        [--sequences 06,03] [--repeats 3] [--masker outline]

Then the same frames run as two jobs alone, one after the other: the masking alone
(``mask_sequence``: read + detect + masks, no SLAM) and the SLAM alone (``run --masker
none``: read + features + stereo + tracking + local mapping, its BA worker).  Their CPU per
frame, added, is what the full pipeline must spend at least (``sum of parts``); divided by
the cores it bounds the frame rate (``bound_fps`` = cores / CPU per frame): how close the
pipeline gets to it is ``pipeline fps / bound_fps``.  Each alone job's ``read`` is counted
once (the masking job reads; the SLAM's own read is taken off); the motion test (2-5 ms a
frame) is in the pipeline only.  CPU a frame is counted over the frame loop (first frame to
last, the process and its live BA workers): start-up, model and vocabulary loading are
left out.

Last, ``dynastereo run`` itself (its own process, as a user runs it) with the masker and
with ``--masker none``: ``summary.fps``, medians over the repeats.

Prints a table per sequence (medians over the repeats) and writes
benchmarks/results/profile.json.

**The SLAM's stages** (``--part stages``, "profile first"): the SLAM alone
(``masker none``) driven frame by frame from this process, with ``slam.threads 1`` (the
right image's ORB not on a second thread), ``slam.local_ba inline`` (the BA solve in
this thread) and ``slam.local_mapping inline`` (local mapping in this thread), so that every
stage's CPU is this thread's.  Each
stage is an entry point of the SLAM (``STAGES``: a method or module function, patched
with a thin timing wrapper); its CPU (``time.process_time``, so native pools count too)
is *exclusive*: what a nested stage spends is its own, not its caller's, and what no
stage claims stays with ``other`` (``System.track``'s own work: the self-calibration's
per-frame part, the motion update...).  Reading the images is outside.  A second pass
counts the calls each stage makes (``sys.setprofile``: every Python function call and
every call of a builtin / C function from Python -- ``cv2``, ``gtsam`` and numpy's
builtin functions; numpy's ufuncs and operators, and calls into compiled kernels, fire
no event) -- the Python-level overhead a compiled kernel removes.  Per frame: totals
over the clip / its frames; medians of ``--repeats`` for the CPU, the counts are the
same every time.  Entry points that no longer exist are listed as ``missing``.

    DYNASTEREO_DATA=... .venv/bin/python benchmarks/bench_profile.py --part stages [--sequences 06,03]

(``--part budget``: the parts above only; ``--part all``, the default: both.  A part run
alone keeps the other's figures in the JSON.)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from _common import data_dir, load, machine, models_dir, now, results_path, write_json
from _shared_cpu import LoopCpu, children_cpu
from dynastereo.api import mask_sequence, run_sequence
from dynastereo.config import Config

RESULTS = results_path("profile")
TICK = os.sysconf("SC_CLK_TCK")


def _thread_cpu() -> dict[str, float]:
    """CPU seconds per thread name of this process (threads of one name summed)."""
    names = {t.native_id: t.name for t in threading.enumerate()}
    out: dict[str, float] = {}
    for d in Path("/proc/self/task").iterdir():
        try:
            fields = (d / "stat").read_text().rsplit(")", 1)[1].split()
            comm = (d / "comm").read_text().strip()
        except OSError:
            continue
        cpu = (int(fields[11]) + int(fields[12])) / TICK  # utime + stime
        name = names.get(int(d.name), f"native:{comm}")
        key = name.rsplit("_", 1)[0] if name.startswith(("prefetch", "features", "local-mapping", "selfcal-ba")) else name
        key = "prefetch" if key == "dynastereo-mask" else key  # the runtime's masking thread
        out[key] = out.get(key, 0.0) + cpu
    return out


class ThreadSampler:
    """Observer: the threads' CPU times after every frame (the prefetch thread ends with the
    run, so it is read while the run goes on; the largest value of each thread is kept)."""

    def __init__(self) -> None:
        self.cpu: dict[str, float] = {}

    def on_frame(self, event) -> None:
        for k, v in _thread_cpu().items():
            self.cpu[k] = max(self.cpu.get(k, 0.0), v)


def profile_once(seq: Path, cfg: Config, models: Path | None) -> dict:
    before_t, before_c = _thread_cpu(), children_cpu()
    sampler, loop = ThreadSampler(), LoopCpu()
    with tempfile.TemporaryDirectory() as tmp:
        res = run_sequence(seq, Path(tmp) / "run", cfg, models_dir=models, observers=(sampler, loop), overwrite=True)
        timing = json.loads((Path(tmp) / "run" / "timing.json").read_text())
    after_t, after_c = {**sampler.cpu, **_thread_cpu()}, children_cpu()
    threads = {k: round(v - before_t.get(k, 0.0), 2) for k, v in after_t.items() if v - before_t.get(k, 0.0) > 0.005}
    workers = round(after_c - before_c, 2)
    total = sum(threads.values()) + workers
    cores = os.cpu_count() or 1
    return {
        "frames": len(res.frames),
        "wall_s": round(res.wall_s, 2),
        "fps": round(res.fps, 2),
        "cpu_threads_s": dict(sorted(threads.items(), key=lambda kv: -kv[1])),
        "cpu_workers_s": workers,
        "cpu_total_s": round(total, 2),
        "loop_cpu_ms": round(loop.ms_per_frame, 1),
        "cores_used": round(total / res.wall_s, 2) if res.wall_s > 0 else None,
        "share_of_cores": round(total / (res.wall_s * cores), 3) if res.wall_s > 0 else None,
        "stage_median_ms": {k: v["median"] for k, v in timing["summary"].items() if isinstance(v, dict)},
    }


def alone_once(seq: Path, cfg: Config, models: Path | None) -> dict:
    """CPU (this process + its workers) per frame and stage medians of the masking job
    alone and of the SLAM job alone (``masker none``), on the same frames."""
    lm, ls = LoopCpu(), LoopCpu()
    with tempfile.TemporaryDirectory() as tmp:
        m = mask_sequence(seq, Path(tmp) / "mask", cfg, models_dir=models, observers=(lm,), overwrite=True)
        w1 = children_cpu()
        s = run_sequence(seq, Path(tmp) / "slam", cfg.with_overrides({"masker.kind": "none"}), models_dir=models,
                         observers=(ls,), overwrite=True)
        w2 = children_cpu()
        mask_t = json.loads((Path(tmp) / "mask" / "timing.json").read_text())["summary"]
        slam_t = json.loads((Path(tmp) / "slam" / "timing.json").read_text())["summary"]
    n_m, n_s = len(m.frames_done), len(s.frames)
    slam_read = slam_t["read"]["mean"]  # read once: the masking job's
    mask_ms = lm.ms_per_frame
    slam_ms = ls.ms_per_frame - slam_read
    return {
        "mask_cpu_ms": round(mask_ms, 1),
        "mask_fps": round(n_m / m.wall_s, 2),
        "slam_cpu_ms": round(slam_ms, 1),
        "slam_ba_cpu_ms": round((w2 - w1) / n_s * 1e3, 1),  # the workers' whole lives
        "slam_fps": round(s.fps, 2),
        "sum_cpu_ms": round(mask_ms + slam_ms, 1),
        "stage_median_ms": {**{k: v["median"] for k, v in mask_t.items() if isinstance(v, dict)},
                            **{k: v["median"] for k, v in slam_t.items() if isinstance(v, dict) and k != "read"}},
    }


def cli_fps(seq: Path, masker: str, tmp: Path) -> float:
    """``summary.fps`` of ``dynastereo run`` as a user runs it (its own process)."""
    out = tmp / f"cli_{masker}"
    subprocess.run([str(Path(sys.executable).with_name("dynastereo")), "run", str(seq), "-o", str(out), "--masker",
                    masker, "--overwrite"], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return float(json.loads((out / "timing.json").read_text())["summary"]["fps"])


def _median_dict(rows: list[dict]) -> dict:
    keys = {k for r in rows for k in r}
    return {k: round(float(np.median([r.get(k, 0.0) for r in rows])), 2) for k in sorted(keys)}


# ---------------------------------------------------------------- the SLAM's stages
# (module, attribute path, stage): the SLAM's entry points, in the order of a frame
STAGES = [
    ("dynastereo.slam.orb", "ORBExtractor.extract", "ORB extraction"),
    ("dynastereo.slam.tracking", "stereo_match", "stereo matching"),
    ("dynastereo.slam.tracking", "Tracker.make_frame", "frame setup (selfcal, Frame)"),
    ("dynastereo.slam.tracking", "Tracker.track_motion_model", "pose prediction + search by projection"),
    ("dynastereo.slam.tracking", "Tracker.track_reference_keyframe", "pose prediction + search by projection"),
    ("dynastereo.slam.tracking", "Tracker.optimize_frame", "pose optimization"),
    ("dynastereo.slam.tracking", "Tracker.track_local_map", "local map tracking"),
    ("dynastereo.slam.tracking", "relocalize_frame", "relocalization"),
    ("dynastereo.slam.tracking", "Tracker.need_new_keyframe", "keyframe decision"),
    ("dynastereo.slam.tracking", "Tracker._create_keyframe", "keyframe creation"),
    ("dynastereo.slam.local_mapping", "LocalMapper.process", "local mapping: map updates"),
    ("dynastereo.slam.local_mapping", "LocalMapper.create_new_points", "local mapping: triangulation"),
    ("dynastereo.slam.local_mapping", "LocalMapper.fuse", "local mapping: fusion"),
    ("dynastereo.slam.local_mapping", "LocalMapper.cull_points", "local mapping: culling"),
    ("dynastereo.slam.local_mapping", "LocalMapper.cull_keyframes", "local mapping: culling"),
    ("dynastereo.slam.local_mapping", "LocalMapper.build_problem", "local BA: build"),
    ("dynastereo.slam.local_mapping", "LocalMapper.build_selfcal_problem", "local BA: build"),
    ("dynastereo.slam.local_mapping", "run_ba", "local BA: solve"),
    ("dynastereo.slam.local_mapping", "LocalMapper._apply", "local BA: apply"),
    ("dynastereo.slam.active_map", "ActiveMap.place_keyframe", "loop closing + keyframe DB"),
    # the map's bookkeeping, wherever it is called from (nested: its time leaves the caller's)
    ("dynastereo.slam.map", "Map.update_points", "map: normals, distances, descriptors (update_points)"),
    ("dynastereo.slam.map", "Map.add_observations", "map: add / erase / fuse observations"),
    ("dynastereo.slam.map", "Map.erase_observations", "map: add / erase / fuse observations"),
    ("dynastereo.slam.map", "Map.set_bad", "map: add / erase / fuse observations"),
    ("dynastereo.slam.map", "Map.replace", "map: add / erase / fuse observations"),
    ("dynastereo.slam.map", "Map.update_connections", "map: covisibility (update_connections)"),
    ("dynastereo.slam.observations", "Observations.rows_of", "map: observation rows (rows_of)"),
    ("dynastereo.slam.loop_closing", "LoopCloser.collect", "loop closing + keyframe DB"),
]
OTHER = "other"
STAGE_ORDER = list(dict.fromkeys([s for *_x, s in STAGES] + [OTHER]))


class StageClock:
    """Exclusive CPU time and call counts per stage (module doc, ``--part stages``)."""

    def __init__(self) -> None:
        self.cpu: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self.entries: dict[str, int] = {}
        self.stack: list[list] = []  # [stage, start cpu, cpu of nested stages]
        self.wrappers: set = set()

    @contextmanager
    def stage(self, name: str):
        t0 = time.process_time()
        self.stack.append([name, t0, 0.0])
        self.entries[name] = self.entries.get(name, 0) + 1
        try:
            yield
        finally:
            _, start, nested = self.stack.pop()
            dt = time.process_time() - start
            self.cpu[name] = self.cpu.get(name, 0.0) + dt - nested
            if self.stack:
                self.stack[-1][2] += dt

    def wrap(self, fn, name: str):
        clock = self

        def timed(*a, **k):
            with clock.stage(name):
                return fn(*a, **k)

        self.wrappers.add(timed.__code__)
        return timed

    def profiler(self, frame, event, arg) -> None:
        if event in ("call", "c_call") and self.stack:
            if event == "call" and (frame.f_code in self.wrappers or frame.f_code.co_name in ("stage", "__enter__",
                                                                                                "__exit__")):
                return
            top = self.stack[-1][0]
            self.calls[top] = self.calls.get(top, 0) + 1


@contextmanager
def hooked(clock: StageClock):
    """Patch the entry points of ``STAGES`` with ``clock``'s wrappers; yields the missing ones."""
    import importlib

    undo, missing = [], []
    for mod_name, attr, name in STAGES:
        mod = importlib.import_module(mod_name)
        *path, last = attr.split(".")
        owner = mod
        for p in path:
            owner = getattr(owner, p, None)
        fn = getattr(owner, last, None) if owner is not None else None
        if fn is None:
            missing.append(f"{mod_name}.{attr}")
            continue
        raw = owner.__dict__[last] if isinstance(owner, type) else fn
        setattr(owner, last, clock.wrap(fn, name))
        undo.append((owner, last, raw))
    try:
        yield missing
    finally:
        for owner, last, raw in reversed(undo):
            setattr(owner, last, raw)


def stages_once(seq_dir: Path, count_calls: bool) -> dict:
    """One pass of the SLAM alone over the clip (module doc): per stage, CPU ms and
    calls over the whole clip; and the frames."""
    from dynastereo.io import open_sequence
    from dynastereo.slam import System

    seq = open_sequence(seq_dir)
    cfg = Config().with_overrides({"masker.kind": "none", "slam.threads": 1, "slam.local_ba": "inline",
                                   "slam.local_mapping": "inline"})
    clock = StageClock()
    n = len(seq)
    with hooked(clock) as missing:
        system = System(cfg, seq.calibration)
        total = 0.0
        try:
            for i in range(n):
                f = seq.frame(i)
                t0 = time.process_time()
                if count_calls:
                    sys.setprofile(clock.profiler)
                try:
                    with clock.stage(OTHER):
                        system.track(f, None)
                finally:
                    if count_calls:
                        sys.setprofile(None)
                total += time.process_time() - t0
            lost = len(system.lost_frames())
        finally:
            system.shutdown()
    return {"frames": n, "lost": lost, "cpu_ms": {k: v * 1e3 for k, v in clock.cpu.items()},
            "calls": dict(clock.calls), "entries": dict(clock.entries), "total_cpu_ms": total * 1e3,
            "missing": missing}


def slam_stages(seq_dir: Path, repeats: int) -> dict:
    """The stage table of one clip: CPU ms a frame (median of ``repeats`` passes) and
    Python-level calls a frame (a separate counting pass)."""
    timed = [stages_once(seq_dir, False) for _ in range(repeats)]
    counted = stages_once(seq_dir, True)
    n = timed[0]["frames"]
    rows = []
    for st in STAGE_ORDER:
        cpu = float(np.median([t["cpu_ms"].get(st, 0.0) for t in timed])) / n
        rows.append({"stage": st, "cpu_ms_per_frame": round(cpu, 2),
                     "calls_per_frame": round(counted["calls"].get(st, 0) / n, 1),
                     "entries_per_frame": round(counted["entries"].get(st, 0) / n, 2)})
    total = float(np.median([t["total_cpu_ms"] for t in timed])) / n
    return {"frames": n, "lost": timed[0]["lost"], "repeats": repeats, "total_cpu_ms_per_frame": round(total, 1),
            "calls_per_frame": round(sum(counted["calls"].values()) / n, 1),
            "rows": rows, "missing": timed[0]["missing"],
            "cpu_ms_runs": [round(t["total_cpu_ms"] / n, 1) for t in timed]}


def print_stages(name: str, r: dict) -> None:
    print(f"\nKITTI {name}, the SLAM alone (--masker none; one thread, local BA inline): {r['frames']} frames, "
          f"{r['total_cpu_ms_per_frame']} ms CPU a frame, {r['calls_per_frame']:.0f} Python-level calls a frame")
    print("| stage | CPU ms / frame | share | Python-level calls / frame | entries / frame |")
    print("|---|---:|---:|---:|---:|")
    tot = sum(x["cpu_ms_per_frame"] for x in r["rows"]) or 1.0
    for x in r["rows"]:
        print(f"| {x['stage']} | {x['cpu_ms_per_frame']:.1f} | {100 * x['cpu_ms_per_frame'] / tot:.0f} % | "
              f"{x['calls_per_frame']:.0f} | {x['entries_per_frame']:.2f} |")
    if r["missing"]:
        print("missing entry points (not timed): " + ", ".join(r["missing"]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sequences", default="06,03")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--masker", default="outline")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--part", choices=("all", "budget", "stages"), default="all",
                    help="budget: the threads and parts of a run; stages: the SLAM's stage table; all: both")
    args = ap.parse_args()
    data = data_dir()
    kept = json.loads(args.out.read_text()) if args.out.exists() else {}
    if args.part in ("all", "stages"):
        stages = {"method": "exclusive process CPU per SLAM entry point (bench_profile.py doc), masker none, "
                            "slam.threads 1, slam.local_ba inline, slam.local_mapping inline; calls: sys.setprofile call + c_call events",
                  "date": now(), "load_before": load(),
                  "sequences": {}}
        for name in args.sequences.split(","):
            seq = data / "kitti_odometry" / "dataset" / "sequences" / name
            r = slam_stages(seq, args.repeats)
            stages["sequences"][name] = r
            print_stages(name, r)
        stages["load_after"] = load()
        kept["slam_stages"] = stages
        if args.part == "stages":
            write_json(args.out, kept)
            print(f"-> {args.out}")
            return
    models = models_dir(required=False)
    cfg = Config().with_overrides({"masker.kind": args.masker})
    out = {"masker": args.masker, "repeats": args.repeats, "machine": machine(),
           "load_before": load(), "sequences": {}}
    if "slam_stages" in kept:
        out["slam_stages"] = kept["slam_stages"]
    for name in args.sequences.split(","):
        seq = data / "kitti_odometry" / "dataset" / "sequences" / name
        runs = [profile_once(seq, cfg, models) for _ in range(args.repeats)]
        med = {
            "fps": round(float(np.median([r["fps"] for r in runs])), 2),
            "wall_s": round(float(np.median([r["wall_s"] for r in runs])), 2),
            "cores_used": round(float(np.median([r["cores_used"] for r in runs])), 2),
            "cpu_threads_s": _median_dict([r["cpu_threads_s"] for r in runs]),
            "cpu_workers_s": round(float(np.median([r["cpu_workers_s"] for r in runs])), 2),
            "stage_median_ms": _median_dict([r["stage_median_ms"] for r in runs]),
        }
        alone = [alone_once(seq, cfg, models) for _ in range(args.repeats)]
        a = {k: round(float(np.median([r[k] for r in alone])), 2) for k in alone[0] if k != "stage_median_ms"}
        a["stage_median_ms"] = _median_dict([r["stage_median_ms"] for r in alone])
        cores = os.cpu_count() or 1
        pipe_cpu = float(np.median([r["loop_cpu_ms"] for r in runs]))
        bound = {
            "pipeline_cpu_ms": round(pipe_cpu, 1),
            "sum_of_parts_cpu_ms": a["sum_cpu_ms"],
            "bound_fps": round(cores * 1e3 / a["sum_cpu_ms"], 2),
            "fps_over_bound": round(med["fps"] / (cores * 1e3 / a["sum_cpu_ms"]), 2),
            "cpu_over_parts": round(pipe_cpu / a["sum_cpu_ms"], 2),
        }
        with tempfile.TemporaryDirectory() as tmp:
            cli = {m: [cli_fps(seq, m, Path(tmp)) for _ in range(args.repeats)] for m in (args.masker, "none")}
        bound["cli_fps"] = {m: round(float(np.median(v)), 2) for m, v in cli.items()}
        bound["cli_fps_runs"] = cli
        out["sequences"][name] = {"median": med, "alone": a, "bound": bound, "runs": runs, "alone_runs": alone}
        print(f"KITTI {name}: {runs[0]['frames']} frames, {med['fps']} FPS, wall {med['wall_s']} s, "
              f"{med['cores_used']} of {os.cpu_count()} cores busy")
        for k, v in med["cpu_threads_s"].items():
            print(f"  thread {k:<28} {v:7.2f} s CPU")
        print(f"  BA worker processes           {med['cpu_workers_s']:7.2f} s CPU")
        print("  stage medians (ms): " + ", ".join(f"{k} {v}" for k, v in med["stage_median_ms"].items()))
        print(f"  alone: masking {a['mask_cpu_ms']} ms CPU a frame ({a['mask_fps']} FPS), SLAM {a['slam_cpu_ms']} ms "
              f"(BA {a['slam_ba_cpu_ms']}; {a['slam_fps']} FPS); sum {a['sum_cpu_ms']} ms -> at most "
              f"{bound['bound_fps']} FPS on {cores} cores")
        print(f"  pipeline: {bound['pipeline_cpu_ms']} ms CPU a frame = {bound['cpu_over_parts']}x the parts; "
              f"{med['fps']} FPS = {bound['fps_over_bound']} of the bound")
        print(f"  dynastereo run (CLI): {bound['cli_fps'][args.masker]} FPS, --masker none "
              f"{bound['cli_fps']['none']} FPS")
        print("  alone stage medians (ms): " + ", ".join(f"{k} {v}" for k, v in a["stage_median_ms"].items()))
    out["load_after"] = load()
    write_json(args.out, out)
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
