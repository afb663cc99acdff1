"""The peer system the benchmarks measure against: ORB-SLAM3 stereo through ``pyorbslam3``
(GPL-3, its own venv, run as a subprocess, never imported): where it is looked for
(:func:`add_peer_args`, :func:`find_peer`) and one run of it (:func:`run_peer`).  How it
is installed: ``../shared/anchors/README.md``."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
from pathlib import Path

from _common import DEFAULT_DATA, ROOT, data_dir
from _shared_runs import ate


def add_peer_args(ap: argparse.ArgumentParser) -> Path | None:
    """The peer's options (``--peer-python``, ``--peer-script``, ``--vocabulary``; see
    ``bench_peers.py``); returns the data folder (:func:`_common.data_dir`, ``None`` when
    there is none: :func:`_common.clip_dirs` then says so)."""
    up = ROOT.parent
    data = data_dir(required=False)
    ap.add_argument("--peer-python", type=Path,
                    default=Path(os.environ.get("DYNASTEREO_PEER_PYTHON", up / ".venv-peers" / "bin" / "python")))
    ap.add_argument("--peer-script", type=Path, default=Path(
        os.environ.get("DYNASTEREO_PEER_SCRIPT", (data or DEFAULT_DATA).parent / "anchors" / "pyorbslam3_run.py")))
    ap.add_argument("--vocabulary", type=Path,
                    default=Path(os.environ.get("DYNASTEREO_PEER_VOCAB", up / ".peers" / "ORBvoc.txt")))
    return data


def find_peer(args) -> tuple[dict | None, str]:
    """(the peer's python, script and vocabulary, "") or (None, why it is skipped)."""
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
    """One ORB-SLAM3 run on ``seq`` (its trajectory ``tmp/orbslam3.kitti.txt``): frames,
    FPS, CPU ms a frame, ATE against ``gt``, frames lost."""
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
