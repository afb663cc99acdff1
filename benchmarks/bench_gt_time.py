"""KITTI raw 0001's ground truth at the images' times against the devkit's: what it changes, and what is left.

The synced download pairs each image with the OXTS packet nearest in time (-4.7 to +4.7 ms
off on drive 0001); ``dynastereo.io.kitti_raw`` moves each packet's pose to its image's
stamp (``at="images"``, the default) -- ``at="packets"`` keeps the devkit's poses.  This
benchmark runs ``dynastereo run`` (default pipeline) once per ``slam.n_features`` variant
(2000, 1950, 2050, 2100, as ``bench_objects.py``) and, when its venv is there, ORB-SLAM3
through pyorbslam3 (``--peer-repeats`` runs; ``bench_peers.py`` says how it is installed),
and evaluates every trajectory against both ground truths:

* ATE (APE RMSE, SE(3)-aligned) and start-anchored end-point drift (% of the path);
* the end point's error split along the last step of the path, across it (left) and
  vertically, metres: what an error in the ground truth's own camera frame would show as
  the same lateral and vertical error in every run of every system;
* the along-track error's frame-to-frame saw-tooth: the median absolute change of the
  along-track error between consecutive frames (a timing error of the ground truth moves
  it by up to ``v * 9.4 ms`` from frame to frame).

Prints the medians, writes ``benchmarks/results/gt_time.json``.  Run:

    DYNASTEREO_DATA=/work/shared/data DYNASTEREO_MODELS=/work/shared/models \\
        .venv/bin/python benchmarks/bench_gt_time.py [--variants 2000,1950,2050,2100] [--peer-repeats 3]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from _common import CLIPS, data_dir, data_path, machine, median, now, print_table, results_path, write_json
from _shared_peer import add_peer_args, find_peer, run_peer
from _shared_runs import ate_drift, run_dynastereo

OUT = results_path("gt_time")


def end_split(est: np.ndarray, gt: np.ndarray) -> dict:
    """Start-anchored end-point error of ``est`` against ``gt`` (N, 4, 4, camera frame: x
    right, y down, z forward) along the path's last step, to its left and up; and the
    along-track error's median frame-to-frame change."""
    n = min(len(est), len(gt))
    E = np.linalg.inv(est[0]) @ est[:n]
    G = np.linalg.inv(gt[0]) @ gt[:n]
    err = E[:, :3, 3] - G[:, :3, 3]
    step = G[1:, :3, 3] - G[:-1, :3, 3]
    along = step / np.maximum(np.linalg.norm(step, axis=1), 1e-9)[:, None]
    along = np.vstack([along[:1], along])  # per frame: the step that reached it
    up = np.array([0.0, -1.0, 0.0])
    left = np.cross(up, along[-1])
    left /= np.linalg.norm(left)
    a = np.einsum("ij,ij->i", err, along)
    return {"along_m": float(err[-1] @ along[-1]), "left_m": float(err[-1] @ left), "up_m": float(err[-1] @ up),
            "sawtooth_m": float(np.median(np.abs(np.diff(a))))}


def evaluate_both(traj: Path, gts: dict) -> dict:
    from dynastereo.eval.trajectory import read_trajectory

    est = read_trajectory(traj)
    return {at: {**ate_drift(est, g), **{k: round(v, 4) for k, v in end_split(est.poses, g.poses).items()}}
            for at, g in gts.items()}


def _median(rows: list[dict], at: str, key: str) -> float:
    return median(r[at][key] for r in rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--variants", default="2000,1950,2050,2100", help="slam.n_features per dynastereo run")
    ap.add_argument("--peer-repeats", type=int, default=3, help="ORB-SLAM3 runs (0: none)")
    add_peer_args(ap)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    data = data_dir()

    from dynastereo.api import ground_truth

    seq = data_path(CLIPS["raw0001"], data=data)
    gts = {at: ground_truth(seq, at=at) for at in ("images", "packets")}
    runs: dict[str, list[dict]] = {"dynastereo": [], "orbslam3": []}
    notes = []
    peer = None
    if args.peer_repeats > 0:
        peer, why = find_peer(args)
        if peer is None:
            print(why, flush=True)
            notes.append(why)
    with tempfile.TemporaryDirectory(prefix="gt-time-") as tmp:
        for nf in [int(v) for v in args.variants.split(",")]:
            out = Path(tmp) / f"dyn_{nf}"
            run_dynastereo(seq, out, nf)
            r = {"n_features": nf, **evaluate_both(out / "trajectory.kitti.txt", gts)}
            runs["dynastereo"].append(r)
            print(f"dynastereo n_features {nf}: " + _line(r), flush=True)
        for rep in range(args.peer_repeats if peer else 0):
            d = Path(tmp) / f"peer_{rep}"
            d.mkdir()
            run_peer(seq, d, None, peer)
            r = {"repeat": rep, **evaluate_both(d / "orbslam3.kitti.txt", gts)}
            runs["orbslam3"].append(r)
            print(f"ORB-SLAM3 run {rep + 1}: " + _line(r), flush=True)
    keys = ("ate_m", "drift_percent", "along_m", "left_m", "up_m", "sawtooth_m")
    summary = {s: {at: {k: _median(rs, at, k) for k in keys} for at in gts} for s, rs in runs.items() if rs}
    result = {"date": now(),
              "machine": machine(),
              "ground_truth": {"images": "OXTS poses moved to the images' stamps (dynastereo default)",
                               "packets": "the devkit's poses, at the packets' stamps"},
              "notes": notes, "summary": summary, "runs": runs}
    write_json(args.out, result)
    print("\nKITTI raw 0001, medians: ATE m / drift % / end-point error along, left, up (m) / along-track saw-tooth (m)")
    print_table(("system", "ground truth", "ATE (m)", "drift", "end along", "end left", "end up", "saw-tooth"),
                [(s, at, f"{m['ate_m']:.4f}", f"{m['drift_percent']:.3f} %", f"{m['along_m']:+.3f}", f"{m['left_m']:+.3f}",
                  f"{m['up_m']:+.3f}", f"{m['sawtooth_m']:.3f}") for s, per in summary.items() for at, m in per.items()])
    print(f"-> {args.out}")
    return 0


def _line(r: dict) -> str:
    return "  ".join(f"{at}: ATE {m['ate_m']:.4f} m drift {m['drift_percent']:.3f} % end along {m['along_m']:+.3f} "
                     f"left {m['left_m']:+.3f} up {m['up_m']:+.3f} saw-tooth {m['sawtooth_m']:.3f}"
                     for at, m in r.items() if isinstance(m, dict))


if __name__ == "__main__":
    raise SystemExit(main())
