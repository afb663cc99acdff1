"""The SLAM's accuracy with the fast masking settings against the defaults.

The fast masking settings (``detector: {runtime: auto, band_top: 0.25, carry_downscale:
2}``: OpenVINO bf16, the band canvas, the carrying's flow at half size) cut masking CPU
by 20-30 % with recall / IoU held; this benchmark asks whether they keep the SLAM's
trajectory.  Per sequence (KITTI raw drive 0001 against its OXTS ground truth, KITTI
odometry 06 and 03 against their poses) and per setting, one ``run_sequence`` per
``slam.n_features`` variant (2000, 1950, 2050, 2100: a short clip's ATE moves by tens of
per cent with a few more or fewer features, docs/design/slam-accuracy.md), then the medians of
ATE (APE RMSE, SE(3)-aligned) and drift (% of the path, start-anchored) over the
variants.  The runs are deterministic, so the load of a shared machine moves only their
times (reported: process time of the whole run, beside the wall time).

Settings (``--settings``, comma-separated): ``default`` (the Config defaults),
``fast`` (the three fast settings), ``none`` (masking off), ``ov`` / ``band`` /
``carry`` (one fast setting alone over the defaults), ``fast_no_ov`` / ``fast_no_band``
/ ``fast_no_carry`` (the fast settings less one), ``three_channels`` (grey frames fed to
the network as three equal channels, rather than the one-channel grey-input graph),
``stereo2`` (the masks' disparity on half-size images, ``stereo.scale: 2``),
``fast_stereo2`` (both).  Extra overrides for every run:
``--set key=value`` (repeatable).

Prints a table of medians; writes ``benchmarks/results/fast_masking.json`` (``--out``).
Run outputs stay under ``--work`` (for comparing masks / verdicts afterwards).

    DYNASTEREO_DATA=/work/shared/data DYNASTEREO_MODELS=/work/shared/models \\
        .venv/bin/python benchmarks/bench_fast_masking.py [--seqs raw0001,06,03] [--settings default,fast,none]
"""

from __future__ import annotations

import argparse
import json
import logging
import resource
import tempfile
import time
from pathlib import Path

from _common import CLIPS, data_dir, machine, median, results_path, write_json
from dynastereo.api import run_sequence
from dynastereo.config import Config
from dynastereo.eval import evaluate_files
from dynastereo.eval.trajectory import find_ground_truth

OUT = results_path("fast_masking")
FAST = {"detector.runtime": "auto", "detector.band_top": 0.25, "detector.carry_downscale": 2}
SLOW = {"detector.runtime": "onnxruntime", "detector.band_top": 0.0, "detector.carry_downscale": 1}
SETTINGS = {
    "default": {},
    "accurate": dict(SLOW),  # the earlier, slower defaults, explicit
    "fast": dict(FAST),
    "none": {"masker.kind": "none"},
    "ov": {**SLOW, "detector.runtime": "auto"},
    "band": {**SLOW, "detector.band_top": 0.25},
    "carry": {**SLOW, "detector.carry_downscale": 2},
    "fast_no_ov": {**FAST, "detector.runtime": "onnxruntime"},
    "fast_no_band": {**FAST, "detector.band_top": 0.0},
    "fast_no_carry": {**FAST, "detector.carry_downscale": 1},
    "three_channels": {"detector.grey_input": False},  # grey frames as three equal channels (not the one-channel graph)
    "stereo2": {"stereo.scale": 2},  # the masks' disparity on half-size images
    "fast_stereo2": {**FAST, "stereo.scale": 2},  # the fast settings and stereo2 (configs/fast.yaml's comments)
}
SEQS = CLIPS


def _median(v):
    return median(v)


def _parse(v: str):
    try:
        return json.loads(v)
    except ValueError:
        return v


def one_run(seq_dir: Path, out: Path, over: dict) -> dict:
    cfg = Config().with_overrides(over)
    c0, t0 = time.process_time(), time.perf_counter()
    res = run_sequence(seq_dir, out, cfg, stereo_check=False, overwrite=True)
    cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    ev = evaluate_files(out / "trajectory.kitti.txt", find_ground_truth(seq_dir))
    return {"frames": len(res.frames), "lost": len(res.lost), "ate_m": round(float(ev.ape["rmse"]), 4),
            "drift_percent": round(float(ev.drift_percent), 3), "cpu_s": round(cpu, 2), "wall_s": round(wall, 2)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seqs", default="raw0001,06,03")
    ap.add_argument("--settings", default="default,fast,none")
    ap.add_argument("--variants", default="2000,1950,2050,2100", help="slam.n_features per run")
    ap.add_argument("--set", action="append", default=[], help="key=value override for every run")
    ap.add_argument("--work", type=Path, default=None, help="run outputs (default: a new temporary folder)")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    logging.getLogger("dynastereo").setLevel(logging.ERROR)
    data = data_dir(required=False)
    if data is None:
        print("skipped: DYNASTEREO_DATA is not set (KITTI raw 0001 and odometry 06 / 03 are needed)")
        return 0
    extra = {k: _parse(v) for k, v in (s.split("=", 1) for s in args.set)}
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_fast_masking_"))
    variants = [int(v) for v in args.variants.split(",") if v]
    settings = [s for s in args.settings.split(",") if s]
    runs: dict[str, dict[str, list[dict]]] = {}
    # alternate the settings inside each (sequence, variant): their CPU times see the same load
    for seq in [s for s in args.seqs.split(",") if s]:
        for nf in variants:
            for name in settings:
                over = {**SETTINGS[name], **extra, "slam.n_features": nf}
                r = {"n_features": nf, **one_run(data / SEQS[seq], work / f"{seq}_{name}_nf{nf}", over)}
                runs.setdefault(seq, {}).setdefault(name, []).append(r)
                print(f"{seq:8s} {name:14s} nf {nf}: ATE {r['ate_m']:.4f} m  drift {r['drift_percent']:.3f} %  "
                      f"lost {r['lost']}  cpu {r['cpu_s']} s  wall {r['wall_s']} s", flush=True)
    med = {seq: {name: {"ate_m": round(_median([r["ate_m"] for r in rs]), 4),
                        "drift_percent": round(_median([r["drift_percent"] for r in rs]), 3),
                        "ate_range": [min(r["ate_m"] for r in rs), max(r["ate_m"] for r in rs)],
                        "cpu_s": round(_median([r["cpu_s"] for r in rs]), 2)}
                 for name, rs in by.items()} for seq, by in runs.items()}
    print("\nmedians over n_features " + args.variants)
    for seq, by in med.items():
        ref = by.get("default", {}).get("ate_m")
        for name, m in by.items():
            ratio = f"  x{m['ate_m'] / ref:.2f} default" if ref else ""
            print(f"  {seq:8s} {name:14s} ATE {m['ate_m']:.4f} m ({m['ate_range'][0]:.4f}-{m['ate_range'][1]:.4f})"
                  f"  drift {m['drift_percent']:.3f} %  cpu {m['cpu_s']} s{ratio}")
    result = {"benchmark": "fast_masking",
              "machine": machine(maxrss_mb=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)),
              "settings": {s: SETTINGS[s] for s in settings}, "extra": extra, "variants": variants,
              "work": str(work), "runs": runs, "medians": med}
    write_json(args.out, result)
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
