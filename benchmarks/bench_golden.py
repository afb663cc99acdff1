"""Golden trajectories (``tests/data/golden/``) and the spread that sets their tolerance.

Four cases, each a ``dynastereo run`` of today's code (the CLI, its own process):

* ``kitti06``: KITTI 06, all 51 frames, the default pipeline (outline masks of what moves,
  yolox-nano from ``$DYNASTEREO_MODELS``);
* ``raw0001``: KITTI raw drive 0001, all 108 frames, the default pipeline (real moving
  traffic; ground truth: its ``oxts/``);
* ``kitti03``: KITTI 03, all 99 frames, ``--masker none`` (the SLAM alone);
* ``convoy``: the synthetic ``convoy`` scenario (``dynastereo.synth.generate``, seed 0,
  640x192, ``CONVOY_FRAMES`` frames), the default pipeline with the ground-truth
  ``oracle`` detector.

For each case the run is repeated with ``slam.n_features`` 1950, 2050 and 2100 (a
change that should not matter, as ``bench_moving.py`` takes it) and each variant's
trajectory is compared with the default's (2000): the RMSE and the largest of the
per-frame camera-position differences, *not aligned* (both start at the identity), and
the ATE of the variant against the default after SE(3) alignment.  The golden test's
tolerance is derived from these figures (see tests/test_golden.py and docs/design/slam-accuracy.md).

``--write`` also (re)writes the golden files from the default run: ``CASE.kitti.txt``
(the run's ``trajectory.kitti.txt``, byte for byte) and ``CASE.json`` (frames lost,
their positions, keyframes, ATE against ground truth).  Prints a table, writes
benchmarks/results/golden_spread.json.  Run:

    DYNASTEREO_DATA=/work/shared/data DYNASTEREO_MODELS=/work/shared/models \\
        .venv/bin/python benchmarks/bench_golden.py [--write] [--cases kitti06,kitti03,convoy]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from _common import ROOT, data_dir, machine, print_table, results_path, write_json

OUT = results_path("golden_spread")
GOLDEN = ROOT / "tests" / "data" / "golden"
VARIANTS = (2000, 1950, 2050, 2100)
CONVOY_FRAMES = 40
CONVOY_SIZE = "640x192"


def case_args(case: str, data: Path, synth_root: Path) -> tuple[Path, list[str], Path | None]:
    """(sequence folder, extra ``dynastereo run`` options, ground-truth file) of a case."""
    kitti = data / "kitti_odometry" / "dataset"
    if case == "kitti06":
        return kitti / "sequences" / "06", [], kitti / "poses" / "06.txt"
    if case == "kitti03":
        return kitti / "sequences" / "03", ["--masker", "none"], kitti / "poses" / "03.txt"
    if case == "raw0001":
        drive = data / "kitti_raw" / "2011_09_26" / "2011_09_26_drive_0001_sync"
        return drive, [], drive  # the ground truth: the drive's oxts/
    if case == "convoy":
        from dynastereo.synth import generate

        seq = synth_root / "convoy" / "sequences" / "00"
        if not (seq / "calib.txt").exists():
            seq = generate(synth_root / "convoy", "convoy", frames=CONVOY_FRAMES, seed=0, size=CONVOY_SIZE)
        return seq, ["--detector", "oracle"], seq.parent.parent / "poses" / "00.txt"
    raise SystemExit(f"unknown case {case!r}: kitti06, raw0001, kitti03 or convoy")


def cli_run(seq: Path, out: Path, extra: list[str], n_features: int | None = None) -> dict:
    """``dynastereo run`` in its own process; returns run.json."""
    cmd = [sys.executable, "-m", "dynastereo.cli.main", "run", str(seq), "--out", str(out), "--overwrite", *extra]
    if n_features is not None and n_features != 2000:
        cfg = out.parent / f"nf{n_features}.yaml"
        cfg.write_text(f"slam:\n  n_features: {n_features}\n")
        cmd += ["--config", str(cfg)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{r.stdout}\n{r.stderr}")
    return json.loads((out / "run.json").read_text())


def compare(est: Path, ref: Path) -> dict:
    """Trajectory ``est`` against ``ref`` (KITTI files, same frames): unaligned position
    RMSE and max (m), and the SE(3)-aligned ATE of est against ref (m)."""
    from dynastereo.eval import evaluate_files

    A = np.loadtxt(est).reshape(-1, 3, 4)
    B = np.loadtxt(ref).reshape(-1, 3, 4)
    a, b = A[:, :, 3], B[:, :, 3]
    d = np.linalg.norm(a - b, axis=1)
    R = np.einsum("nji,njk->nik", B[:, :, :3], A[:, :, :3])
    ang = np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return {"rmse_m": float(np.sqrt(np.mean(d**2))), "max_m": float(d.max()), "rot_max_deg": float(ang.max()),
            "ate_aligned_m": float(evaluate_files(est, ref).ape["rmse"]), "path_m": float(
                np.linalg.norm(np.diff(b, axis=0), axis=1).sum())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default="kitti06,kitti03,convoy")
    ap.add_argument("--write", action="store_true", help="(re)write tests/data/golden/ from the default runs")
    args = ap.parse_args()
    from dynastereo.eval import evaluate_files

    data = data_dir()
    results = json.loads(OUT.read_text()) if OUT.exists() else {}
    results.setdefault("cases", {})
    with tempfile.TemporaryDirectory(prefix="golden-") as tmp:
        tmp = Path(tmp)
        for case in args.cases.split(","):
            seq, extra, gt = case_args(case, data, tmp / "synth")
            runs = {}
            for nf in VARIANTS:
                out = tmp / case / str(nf)
                out.parent.mkdir(parents=True, exist_ok=True)
                run = cli_run(seq, out, extra, nf)
                ate = float(evaluate_files(out / "trajectory.kitti.txt", gt).ape["rmse"])
                runs[nf] = {"frames_lost": run["frames_lost"], "keyframes": run["keyframes"], "ate_gt_m": ate}
                if nf != 2000:
                    runs[nf].update(compare(out / "trajectory.kitti.txt", tmp / case / "2000" / "trajectory.kitti.txt"))
                r = runs[nf]
                vs = (f"vs 2000: rmse {r['rmse_m']:.4f} max {r['max_m']:.4f} aligned {r['ate_aligned_m']:.4f} m "
                      f"rot {r['rot_max_deg']:.3f} deg" if nf != 2000 else "(default)")
                print(f"{case:8s} n_features {nf}: ATE {ate:.4f} m, lost {run['frames_lost']}, {vs}", flush=True)
                if nf == 2000 and args.write:
                    GOLDEN.mkdir(parents=True, exist_ok=True)
                    (GOLDEN / f"{case}.kitti.txt").write_bytes((out / "trajectory.kitti.txt").read_bytes())
                    write_json(GOLDEN / f"{case}.json",
                               {"case": case, "options": extra, "frames": run["frames_done"],
                                "frames_lost": run["frames_lost"], "lost_positions": [x["position"] for x in run["lost"]],
                                "keyframes": run["keyframes"], "ate_gt_m": ate})
            var = [runs[nf] for nf in VARIANTS[1:]]
            results["cases"][case] = {
                "options": extra, "runs": {str(k): v for k, v in runs.items()},
                "spread": {k: max(v[k] for v in var) for k in ("rmse_m", "max_m", "rot_max_deg", "ate_aligned_m")},
            }
    results["variants"] = list(VARIANTS)
    results["machine"] = machine()
    write_json(OUT, results)
    print()
    print_table(("case", "ATE vs GT (2000)", "largest variant vs default: position RMSE / max / aligned ATE (m)",
                 "rotation max (deg)", "lost"),
                [(case, f"{r['runs']['2000']['ate_gt_m']:.4f}",
                  f"{r['spread']['rmse_m']:.4f} / {r['spread']['max_m']:.4f} / {r['spread']['ate_aligned_m']:.4f}",
                  f"{r['spread']['rot_max_deg']:.3f}", [r["runs"][str(v)]["frames_lost"] for v in VARIANTS])
                 for case, r in results["cases"].items()])
    print(f"-> {OUT}")


if __name__ == "__main__":
    main()
