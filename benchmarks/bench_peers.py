"""dynastereo beside a peer: ORB-SLAM3 stereo (C++) through ``pyorbslam3``, side by side.

Three systems (a fourth on request) on each clip (``--clips``: KITTI odometry 06 and 03, KITTI raw drive 0001),
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

Prints a markdown table (README "Results beside ORB-SLAM3"), writes benchmarks/results/peers.json.  Run:

    DYNASTEREO_DATA=/work/shared/data DYNASTEREO_MODELS=/work/shared/models \\
        .venv/bin/python benchmarks/bench_peers.py [--repeats 3] [--clips 06,03,raw0001]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "results" / "peers.json"
SYSTEMS = ("none", "default", "fast", "orbslam3")  # fast: -c configs/fast.yaml (not run unless asked)
VOCAB_NAME = "ORBvoc_selftrained_k10L6 (self-trained, k = 10, L = 6, 456,067 words; ../shared/anchors/README.md)"
RAW_NOTE = ("raw 0001: no ground truth from dynastereo's discovery (the drive's OXTS poses need "
            "dynastereo.io.kitti_raw's reader, not on this branch yet); ATE null")


def clip_dirs(data: Path) -> dict[str, Path]:
    return {
        "06": data / "kitti_odometry" / "dataset" / "sequences" / "06",
        "03": data / "kitti_odometry" / "dataset" / "sequences" / "03",
        "raw0001": data / "kitti_raw" / "2011_09_26" / "2011_09_26_drive_0001_sync",
    }


def children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def ground_truth(seq: Path) -> Path | None:
    """What dynastereo finds as the clip's ground truth (None: nothing)."""
    from dynastereo.api import load_sequence, resolve_ground_truth

    try:
        return resolve_ground_truth(None, load_sequence(seq))
    except Exception:  # noqa: BLE001 -- reported as no ground truth
        return None


def ate(est: Path, gt: Path | None) -> tuple[float | None, str | None]:
    if gt is None:
        return None, "no ground truth"
    from dynastereo.eval import evaluate_files

    try:
        return float(evaluate_files(est, gt).ape["rmse"]), None
    except Exception as e:  # noqa: BLE001
        return None, f"{type(e).__name__}: {e}"


def _cli(seq: Path, out: Path, extra: list[str]) -> float:
    """``dynastereo run`` in its own process; its process tree's CPU seconds."""
    cmd = [sys.executable, "-m", "dynastereo.cli.main", "run", str(seq), "-o", str(out), "--overwrite", *extra]
    c0 = children_cpu()
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stderr[-2000:]}")
    return children_cpu() - c0


def run_dynastereo(seq: Path, system: str, tmp: Path, gt: Path | None) -> dict:
    extra = {"none": ["--masker", "none"], "fast": ["-c", str(ROOT / "configs" / "fast.yaml")]}.get(system, [])
    out = tmp / f"{system}"
    cpu_one = _cli(seq, tmp / f"{system}_1", [*extra, "--frames", "1"])
    cpu_all = _cli(seq, out, extra)
    timing = json.loads((out / "timing.json").read_text())
    run = json.loads((out / "run.json").read_text())
    n = int(run["frames_done"])
    a, why = ate(out / "trajectory.kitti.txt", gt)
    return {"frames": n, "fps": float(timing["summary"]["fps"]),
            "cpu_ms": (cpu_all - cpu_one) / max(n - 1, 1) * 1e3, "cpu_total_s": cpu_all, "cpu_startup_s": cpu_one,
            "ate_m": a, "ate_note": why, "lost": int(run["frames_lost"])}


def kitti_layout(seq: Path, tmp: Path) -> Path:
    """The clip in KITTI odometry layout for the peer script: a raw drive's
    ``image_00/data`` / ``image_01/data`` linked, ``P0`` / ``P1`` from ``P_rect_00/01``."""
    if (seq / "calib.txt").exists():
        return seq
    calib = {}
    for line in (seq.parent / "calib_cam_to_cam.txt").read_text().splitlines():
        k, _, v = line.partition(":")
        calib[k.strip()] = v.split()
    d = tmp / "layout"
    d.mkdir(parents=True, exist_ok=True)
    for cam, raw in (("image_0", "image_00"), ("image_1", "image_01")):
        if not (d / cam).exists():
            (d / cam).symlink_to((seq / raw / "data").resolve())
    (d / "calib.txt").write_text(f"P0: {' '.join(calib['P_rect_00'])}\nP1: {' '.join(calib['P_rect_01'])}\n")
    return d


def run_peer(seq: Path, tmp: Path, gt: Path | None, peer: dict) -> dict:
    traj = tmp / "orbslam3.kitti.txt"
    cmd = [peer["python"], peer["script"], str(kitti_layout(seq, tmp)), peer["vocabulary"], str(traj)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    lines = [s for s in r.stdout.splitlines() if s.startswith("{")]
    if r.returncode != 0 or not lines:
        raise RuntimeError(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stderr[-2000:]}")
    res = json.loads(lines[-1])
    a, why = ate(traj, gt) if res["rows"] == res["frames"] else (None, f"{res['rows']} rows for {res['frames']} frames")
    return {"frames": res["frames"], "fps": res["fps"], "cpu_ms": res["cpu_ms"], "ate_m": a, "ate_note": why,
            "lost": res["not_ok"]}


def add_peer_args(ap: argparse.ArgumentParser) -> Path:
    """The peer's options (``--peer-python``, ``--peer-script``, ``--vocabulary``; module
    doc); returns the data folder (``$DYNASTEREO_DATA``, else ``../shared/data``)."""
    up = ROOT.parent
    data = Path(os.environ.get("DYNASTEREO_DATA", up / "shared" / "data"))
    ap.add_argument("--peer-python", type=Path,
                    default=Path(os.environ.get("DYNASTEREO_PEER_PYTHON", up / ".venv-peers" / "bin" / "python")))
    ap.add_argument("--peer-script", type=Path, default=Path(
        os.environ.get("DYNASTEREO_PEER_SCRIPT", data.parent / "anchors" / "pyorbslam3_run.py")))
    ap.add_argument("--vocabulary", type=Path,
                    default=Path(os.environ.get("DYNASTEREO_PEER_VOCAB", up / ".peers" / "ORBvoc.txt")))
    return data


def find_peer(args) -> tuple[dict | None, str]:
    peer = {"python": str(args.peer_python), "script": str(args.peer_script), "vocabulary": str(args.vocabulary)}
    for what, p in (("peer venv python", args.peer_python), ("peer script", args.peer_script),
                    ("ORB vocabulary", args.vocabulary)):
        if not Path(p).exists():
            return None, (f"ORB-SLAM3 (pyorbslam3) skipped: {what} not found at {p} -- install it as "
                          "../shared/anchors/README.md says (its own venv; gunzip the vocabulary)")
    r = subprocess.run([peer["python"], "-c", "import pyorbslam3"], capture_output=True, text=True)
    if r.returncode != 0:
        return None, f"ORB-SLAM3 skipped: {args.peer_python} cannot import pyorbslam3: {r.stderr.strip()[-300:]}"
    return peer, ""


def med(rows: list[dict], key: str) -> float | None:
    v = [r[key] for r in rows if r.get(key) is not None]
    return float(np.median(v)) if v else None


def _f(v: float | None, fmt: str) -> str:
    return "–" if v is None else format(v, fmt)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--clips", default="06,03,raw0001")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--systems", default="none,default,orbslam3", help="of " + ", ".join(SYSTEMS))
    data = add_peer_args(ap)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()

    clips = {k: v for k, v in clip_dirs(data).items() if k in args.clips.split(",")}
    systems = [s for s in args.systems.split(",") if s in SYSTEMS]
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
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="peers-") as tmp:
        for rep in range(args.repeats):
            for c, seq in clips.items():
                for s in systems:
                    d = Path(tmp) / c / s / str(rep)
                    d.mkdir(parents=True, exist_ok=True)
                    t = time.perf_counter()
                    r = run_peer(seq, d, gts[c], peer) if s == "orbslam3" else run_dynastereo(seq, s, d, gts[c])
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
            for s in ("none", "default", "fast"):
                if s in systems:
                    m = summary[c][s]
                    m["fps_ratio"] = m["fps"] / p["fps"] if p["fps"] else None
                    m["cpu_ratio"] = m["cpu_ms"] / p["cpu_ms"] if p["cpu_ms"] else None
    result = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "repeats": args.repeats,
              "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                          "load_before": load_before, "load_after": os.getloadavg()[0]},
              "peer": {"name": "ORB-SLAM3 stereo via pyorbslam3 (GPL-3, own venv)", "script": str(args.peer_script),
                       "vocabulary": VOCAB_NAME} if peer else None,
              "ground_truth": {c: (str(g) if g else None) for c, g in gts.items()},
              "notes": notes, "summary": summary, "runs": runs}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")

    names = {"06": "KITTI 06", "03": "KITTI 03", "raw0001": "raw 0001"}
    print(f"\nFPS / CPU ms a frame / ATE m, medians of {args.repeats}"
          + (" (ratio dynastereo / ORB-SLAM3: FPS, CPU)" if "orbslam3" in systems else ""))
    head = {"none": "`dynastereo run --masker none`", "default": "`dynastereo run`",
            "fast": "`dynastereo run -c configs/fast.yaml`",
            "orbslam3": "ORB-SLAM3 (pyorbslam3)"}
    print("| clip | " + " | ".join(head[s] for s in systems) + " |")
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
