"""The masks' matching block against the images' width, on real frames: KITTI raw 0001 at its own 1242 px and halved.

``stereo.block_size`` (default 15 px, chosen on KITTI) decides the masks, the motion test's
disparity lookups and the objects' positions.  This benchmark runs the default pipeline
(``dynastereo run``) on KITTI raw drive 0001 as it is (1242 x 375) and halved (621 x 188,
INTER_AREA; ``P_rect_00/01`` halved, the same OXTS ground truth; made in a temporary folder
from ``$DYNASTEREO_DATA``), with blocks ``--blocks`` (halved drive) and ``--full-blocks``
(full size), once per ``slam.n_features`` variant (2000, 1950, 2050, 2100), plus
``--masker none``, and reports the ATE (APE RMSE, SE(3)-aligned) and end-point drift against
the OXTS poses at the images' times: medians over the variants.  (The synthetic scenes'
object positions and motion decisions per block: ``bench_objects.py``, ``bench_moving.py``
and docs/design/objects-motion.md.)

Writes ``benchmarks/results/block_size.json``.  Run:

    DYNASTEREO_DATA=/work/shared/data DYNASTEREO_MODELS=/work/shared/models \
        .venv/bin/python benchmarks/bench_block_size.py [--blocks 9,11,13,15] [--variants 2000,1950,2050,2100]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np

from _common import CLIPS, data_path, median, now, print_table, results_path, write_json
from _shared_runs import ate_drift, run_dynastereo

OUT = results_path("block_size")


def halved_drive(drive: Path, work: Path) -> Path:
    """KITTI raw ``drive`` at half size under ``work`` (same layout, calibration halved, its
    ``oxts/`` linked)."""
    date = work / drive.parent.name
    out = date / drive.name
    for name in ("calib_imu_to_velo.txt", "calib_velo_to_cam.txt"):
        (date / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(drive.parent / name, date / name)
    rows = []
    for line in (drive.parent / "calib_cam_to_cam.txt").read_text().splitlines():
        key, _, val = line.partition(":")
        if key.startswith("P_rect_"):
            p = np.array(val.split(), float).reshape(3, 4)
            p[:2] *= 0.5
            p[:2, 2] = (p[:2, 2] * 2 + 0.5) * 0.5 - 0.5  # principal point: pixel centres
            line = key + ": " + " ".join(f"{v:e}" for v in p.ravel())
        elif key.startswith("S_rect_"):
            w, h = (float(v) for v in val.split())
            line = f"{key}: {round(w / 2):e} {round(h / 2):e}"
        rows.append(line)
    (date / "calib_cam_to_cam.txt").write_text("\n".join(rows) + "\n")
    for cam in ("image_00", "image_01"):
        (out / cam / "data").mkdir(parents=True, exist_ok=True)
        shutil.copy(drive / cam / "timestamps.txt", out / cam / "timestamps.txt")
        for f in sorted((drive / cam / "data").glob("*.png")):
            im = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            cv2.imwrite(str(out / cam / "data" / f.name),
                        cv2.resize(im, (round(im.shape[1] / 2), round(im.shape[0] / 2)), interpolation=cv2.INTER_AREA))
    (out / "oxts").symlink_to((drive / "oxts").resolve())
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--blocks", default="9,11,13,15", help="blocks on the halved drive")
    ap.add_argument("--full-blocks", default="11,15", help="blocks on the drive at its own size")
    ap.add_argument("--variants", default="2000,1950,2050,2100", help="slam.n_features per run")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    from dynastereo.api import ground_truth
    from dynastereo.config import StereoConfig
    from dynastereo.eval.trajectory import read_trajectory

    drive = data_path(CLIPS["raw0001"])
    variants = [int(v) for v in args.variants.split(",")]
    sizes = {"full": [int(b) for b in args.full_blocks.split(",")], "half": [int(b) for b in args.blocks.split(",")]}
    table: dict[str, dict[str, list[dict]]] = {}
    with tempfile.TemporaryDirectory(prefix="block-size-") as tmp:
        seqs = {"full": drive, "half": halved_drive(drive, Path(tmp) / "half")}
        for size, seq in seqs.items():
            gt = ground_truth(seq)
            width = cv2.imread(str(next((seq / "image_00" / "data").glob("*.png"))), cv2.IMREAD_GRAYSCALE).shape[1]
            table[size] = {"width": width, "default_block": StereoConfig().block_size}
            for b in [*sizes[size], "none"]:
                rows = []
                for nf in variants:
                    out = Path(tmp) / f"{size}_{b}_{nf}"
                    if b == "none":
                        run_dynastereo(seq, out, nf, extra=("--masker", "none"))
                    else:
                        run_dynastereo(seq, out, nf, int(b))
                    rows.append({"n_features": nf, **ate_drift(read_trajectory(out / "trajectory.kitti.txt"), gt)})
                    print(f"{size} ({width} px) block {b}: n_features {nf} ATE {rows[-1]['ate_m']:.4f} m drift "
                          f"{rows[-1]['drift_percent']:.3f} %", flush=True)
                table[size][str(b)] = {"runs": rows, "ate_m": median(r["ate_m"] for r in rows),
                                       "drift_percent": median(r["drift_percent"] for r in rows)}
    result = {"date": now(), "variants": variants, "results": table}
    write_json(args.out, result)
    print("\nKITTI raw 0001, default pipeline: ATE m / drift %, medians over the variants")
    rows = []
    for size, t in table.items():
        for b, v in t.items():
            if isinstance(v, dict):
                name = "`--masker none`" if b == "none" else b + (" (default)" if int(b) == t["default_block"] else "")
                rows.append((f"{size}, {t['width']} px", name, f"{v['ate_m']:.4f}", f"{v['drift_percent']:.3f} %"))
    print_table(("size", "block", "ATE (m)", "drift"), rows)
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
