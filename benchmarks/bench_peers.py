"""dynastereo beside a peer: ORB-SLAM3 stereo (C++) through ``pyorbslam3``, side by side.

Three systems (a fourth on request) on each clip (``--clips``: KITTI odometry 06 and 03, KITTI raw drive 0001,
and the fast-motion variants ``06x2``, ``03x2``, ``06x3``, ``03x3`` -- every 2nd / 3rd frame of 06 and 03, 2-3 m a
frame as on a highway, made as clips of their own in a temporary folder by :func:`fast_variant`),
one process at a time, alternated (repeat 1: every clip, every system; then repeat 2 ...),
``--repeats`` (default 3) times; medians reported:

* ``none``: ``dynastereo run --masker none`` (the SLAM alone);
* ``default``: ``dynastereo run`` (masking of what moves on, the default detector);
* ``fast`` (only when ``--systems`` names it): ``dynastereo run -c configs/fast.yaml`` (the
  cheaper masking profile);
* ``orbslam3``: ORB-SLAM3 stereo via ``pyorbslam3`` -- the anchors' script
  ``pyorbslam3_run.py`` run as a subprocess with the peer venv's python (never imported
  here: ``pyorbslam3`` is GPL-3, a peer to measure against, not a dependency).

Figures per run:

* **FPS of the frame loop**: dynastereo's own ``timing.json`` ``summary.fps`` (frames /
  wall time from the first frame to the end of the run, models and vocabulary loaded
  before); the peer script's ``fps`` (frames / wall of its track loop, PNG decode inside).
* **CPU ms a frame** (user + system, all threads and child processes -- dynastereo's
  local-BA worker included), start-up left out: dynastereo has no CPU figure of its own
  in ``run.json`` / ``timing.json``, so the CPU of the whole ``dynastereo run`` process
  tree (``getrusage(RUSAGE_CHILDREN)`` around it) of the clip minus that of the same
  command with ``--frames 1`` (start-up, the first frame, shut-down), divided by the
  frames after the first; the peer script's ``cpu_ms`` (``process_time`` over its loop:
  all its threads; it starts no process).
* **ATE**: APE RMSE after SE(3) alignment (``dynastereo.eval.evaluate_files``) against
  the ground truth that dynastereo itself finds for the clip
  (``dynastereo.api.resolve_ground_truth``: KITTI odometry's ``poses/NN.txt``; a raw drive's
  OXTS once ``dynastereo.io.kitti_raw`` reads it -- until then raw 0001's ATE is null,
  with a note).

Ratios dynastereo / peer: FPS (>= 1: dynastereo as fast) and CPU (<= 1: as cheap) of the
medians.  The peer is skipped with a message when its python, script or vocabulary is
missing (how to install: ``../shared/anchors/README.md``).  Where they are looked for:

    --peer-python  $DYNASTEREO_PEER_PYTHON  (default ../.venv-peers/bin/python beside the repo)
    --peer-script  $DYNASTEREO_PEER_SCRIPT  (default $DYNASTEREO_DATA/../anchors/pyorbslam3_run.py)
    --vocabulary   $DYNASTEREO_PEER_VOCAB   (default ../.peers/ORBvoc.txt beside the repo:
                   the anchors' self-trained ORBvoc_selftrained_k10L6.txt.gz, gunzipped)

``--against OTHER/src`` runs each of dynastereo's systems also from another source tree
(``NAME@against``, first on ``PYTHONPATH``), alternated with this tree's in the same pass:
before and after a change, each beside the same peer runs (ORB-SLAM2's extractor on one
pyramid against OpenCV's: ``--against <orb-kernel>/src --out benchmarks/results/peers_orb_kernel.json``).

Prints a markdown table (README "Results beside ORB-SLAM3"), writes benchmarks/results/peers.json
(``--systems default,fast,orbslam3``: benchmarks/results/peers_fast_profile.json).  Run:

    DYNASTEREO_DATA=/work/shared/data DYNASTEREO_MODELS=/work/shared/models \\
        .venv/bin/python benchmarks/bench_peers.py [--repeats 3] [--clips 06,03,raw0001]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import DEFAULT_CLIPS, FAST_VARIANTS, ROOT, clip_dirs, fast_variant, load, machine, median, now, results_path, write_json
from _shared_cpu import children_cpu
from _shared_peer import add_peer_args, find_peer, run_peer
from _shared_runs import ate

OUT = results_path("peers")
SYSTEMS = ("none", "default", "fast", "orbslam3")  # fast: -c configs/fast.yaml (not run unless asked)
VOCAB_NAME = "ORBvoc_selftrained_k10L6 (self-trained, k = 10, L = 6, 456,067 words; ../shared/anchors/README.md)"
RAW_NOTE = ("raw 0001: no ground truth from dynastereo's discovery (the drive's OXTS poses need "
            "dynastereo.io.kitti_raw's reader, not on this branch yet); ATE null")


def ground_truth(seq: Path) -> Path | None:
    """What dynastereo finds as the clip's ground truth (None: nothing)."""
    from dynastereo.api import load_sequence, resolve_ground_truth

    try:
        return resolve_ground_truth(None, load_sequence(seq))
    except Exception:  # noqa: BLE001 -- reported as no ground truth
        return None


def _cli(seq: Path, out: Path, extra: list[str], src: Path | None = None) -> float:
    """``dynastereo run`` in its own process (``src``: another tree's source folder, first on
    ``PYTHONPATH``); its process tree's CPU seconds."""
    cmd = [sys.executable, "-m", "dynastereo.cli.main", "run", str(seq), "-o", str(out), "--overwrite", *extra]
    env = None
    if src is not None:
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(src), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    c0 = children_cpu()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stderr[-2000:]}")
    return children_cpu() - c0


def run_dynastereo(seq: Path, system: str, tmp: Path, gt: Path | None, against: Path | None = None) -> dict:
    """One ``dynastereo run`` of ``system`` (``NAME@against``: ``against``'s source tree)."""
    name, _, other = system.partition("@")
    src = against if other else None
    extra = {"none": ["--masker", "none"], "fast": ["-c", str(ROOT / "configs" / "fast.yaml")]}.get(name, [])
    out = tmp / f"{name}"
    cpu_one = _cli(seq, tmp / f"{name}_1", [*extra, "--frames", "1"], src)
    cpu_all = _cli(seq, out, extra, src)
    timing = json.loads((out / "timing.json").read_text())
    run = json.loads((out / "run.json").read_text())
    n = int(run["frames_done"])
    a, why = ate(out / "trajectory.kitti.txt", gt)
    return {"frames": n, "fps": float(timing["summary"]["fps"]),
            "cpu_ms": (cpu_all - cpu_one) / max(n - 1, 1) * 1e3, "cpu_total_s": cpu_all, "cpu_startup_s": cpu_one,
            "ate_m": a, "ate_note": why, "lost": int(run["frames_lost"])}


def med(rows: list[dict], key: str) -> float | None:
    return median(r.get(key) for r in rows)


def _f(v: float | None, fmt: str) -> str:
    return "–" if v is None else format(v, fmt)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--clips", default=DEFAULT_CLIPS,
                    help="of 06, 03, raw0001 and the fast variants " + ", ".join(FAST_VARIANTS)
                         + " (every 2nd / 3rd frame of 06 and 03)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--systems", default="none,default,orbslam3", help="of " + ", ".join(SYSTEMS))
    data = add_peer_args(ap)
    ap.add_argument("--against", type=Path, default=None,
                    help="another tree's source folder: its runs alternate with this tree's (systems NAME@against)")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()

    wanted = [c.strip() for c in args.clips.split(",") if c.strip()]
    unknown = [c for c in wanted if c not in clip_dirs(data) and c not in FAST_VARIANTS]
    if unknown:
        raise SystemExit(f"unknown clips {unknown}: of 06, 03, raw0001, {', '.join(FAST_VARIANTS)}")
    variants_tmp = tempfile.TemporaryDirectory(prefix="peers-variants-")
    clips = {}
    for c in wanted:
        if c in FAST_VARIANTS:
            base, step = FAST_VARIANTS[c]
            if not clip_dirs(data)[base].exists():
                raise SystemExit(f"clip {base} (for {c}) not found under $DYNASTEREO_DATA={data}")
            clips[c] = fast_variant(clip_dirs(data)[base], step, c, Path(variants_tmp.name))
        else:
            clips[c] = clip_dirs(data)[c]
    systems = [s for s in args.systems.split(",") if s in SYSTEMS]
    if args.against is not None:  # before and after side by side: each of ours also from the other tree
        systems = [x for s in systems for x in ((s,) if s == "orbslam3" else (f"{s}@against", s))]
    notes = []
    peer = None
    if "orbslam3" in systems:
        peer, why = find_peer(args)
        if peer is None:
            print(why, flush=True)
            notes.append(why)
            systems.remove("orbslam3")
    if not systems:
        raise SystemExit("nothing to run (--systems: none, default, orbslam3)")
    missing = [k for k, v in clips.items() if not v.exists()]
    if missing:
        raise SystemExit(f"clips not found under $DYNASTEREO_DATA={data}: {', '.join(missing)}")
    gts = {k: ground_truth(v) for k, v in clips.items()}
    if "raw0001" in clips and gts["raw0001"] is None:
        notes.append(RAW_NOTE)
    runs: dict[str, dict[str, list[dict]]] = {c: {s: [] for s in systems} for c in clips}
    load_before = load()
    with tempfile.TemporaryDirectory(prefix="peers-") as tmp:
        for rep in range(args.repeats):
            for c, seq in clips.items():
                for s in systems:
                    d = Path(tmp) / c / s / str(rep)
                    d.mkdir(parents=True, exist_ok=True)
                    t = time.perf_counter()
                    r = (run_peer(seq, d, gts[c], peer) if s == "orbslam3"
                         else run_dynastereo(seq, s, d, gts[c], args.against))
                    runs[c][s].append(r)
                    print(f"[{rep + 1}/{args.repeats}] {c:7s} {s:8s} {r['fps']:6.2f} FPS  "
                          f"{r['cpu_ms']:6.1f} ms CPU/frame  ATE {_f(r['ate_m'], '.4f')} m  lost {r['lost']}  "
                          f"({time.perf_counter() - t:.0f} s)",
                          flush=True)
    summary: dict[str, dict] = {}
    for c in clips:
        summary[c] = {s: {k: med(runs[c][s], k) for k in ("fps", "cpu_ms", "ate_m")} for s in systems}
        if "orbslam3" in systems:
            p = summary[c]["orbslam3"]
            for s in systems:
                if s != "orbslam3":
                    m = summary[c][s]
                    m["fps_ratio"] = m["fps"] / p["fps"] if p["fps"] else None
                    m["cpu_ratio"] = m["cpu_ms"] / p["cpu_ms"] if p["cpu_ms"] else None
    result = {"date": now(), "repeats": args.repeats,
              "machine": machine(load_before=load_before, load_after=load()),
              "peer": {"name": "ORB-SLAM3 stereo via pyorbslam3 (GPL-3, own venv)", "script": str(args.peer_script),
                       "vocabulary": VOCAB_NAME} if peer else None,
              "ground_truth": {c: (str(g) if g else None) for c, g in gts.items()},
              "against": str(args.against) if args.against else None,
              "notes": notes, "summary": summary, "runs": runs}
    write_json(args.out, result)

    variants_tmp.cleanup()
    names = {"06": "KITTI 06", "03": "KITTI 03", "raw0001": "raw 0001", "06x2": "KITTI 06, every 2nd",
             "03x2": "KITTI 03, every 2nd", "06x3": "KITTI 06, every 3rd", "03x3": "KITTI 03, every 3rd"}
    print(f"\nFPS / CPU ms a frame / ATE m, medians of {args.repeats}"
          + (" (ratio dynastereo / ORB-SLAM3: FPS, CPU)" if "orbslam3" in systems else ""))
    head = {"none": "`dynastereo run --masker none`", "default": "`dynastereo run`",
            "fast": "`dynastereo run -c configs/fast.yaml`",
            "orbslam3": "ORB-SLAM3 (pyorbslam3)"}
    print("| clip | " + " | ".join(head[s.partition("@")[0]] + (" (against)" if "@" in s else "") for s in systems) + " |")
    print("|---|" + "---|" * len(systems))
    for c in clips:
        cells = []
        for s in systems:
            m = summary[c][s]
            cell = f"{_f(m['fps'], '.1f')} / {_f(m['cpu_ms'], '.0f')} / {_f(m['ate_m'], '.3f')}"
            if m.get("fps_ratio") is not None:
                cell += f" ({m['fps_ratio']:.2f}×, {m['cpu_ratio']:.2f}×)"
            cells.append(cell)
        print(f"| {names.get(c, c)} ({runs[c][systems[0]][0]['frames']} fr.) | " + " | ".join(cells) + " |")
    for n in notes:
        print(f"note: {n}")
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
