"""Runs and their evaluation, shared by several benchmarks: ``dynastereo run`` in its own
process (:func:`run_dynastereo`), a trajectory's ATE and drift (:func:`ate_drift`,
:func:`ate`), the cached synthetic sequences (:func:`sequence`), an older commit's ``src``
(:func:`old_tree`, :func:`head_commit`) and the motion test's verdicts on KITTI raw 0001
against its reference labels (:func:`score_raw_labels`)."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RAW_LABELS = ROOT / "tests" / "data" / "raw0001_motion_labels.json"


def run_dynastereo(seq: Path, out: Path, n_features: int, block_size: int | None = None,
                   extra: tuple[str, ...] = ()) -> None:
    """``dynastereo run`` (default pipeline, or as ``extra`` options say) in its own process
    with ``slam.n_features`` (and ``stereo.block_size``) set."""
    cfg = out.parent / f"{out.name}.yaml"
    cfg.write_text(f"slam:\n  n_features: {n_features}\n"
                   + (f"stereo:\n  block_size: {block_size}\n" if block_size is not None else ""))
    cmd = [sys.executable, "-m", "dynastereo.cli.main", "run", str(seq), "-o", str(out), "--overwrite", "-c", str(cfg),
           *extra]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stderr[-2000:]}")


def ate_drift(est, gt) -> dict:
    """ATE (APE RMSE, SE(3)-aligned, m) and end-point drift (%) of trajectory ``est``
    against ``gt``, rounded as the benchmarks' JSON holds them."""
    from dynastereo.eval import evaluate

    ev = evaluate(est, gt)
    return {"ate_m": round(float(ev.ape["rmse"]), 4), "drift_percent": round(float(ev.drift_percent), 3)}


def ate(est: Path, gt: Path | None) -> tuple[float | None, str | None]:
    """(ATE of the trajectory file ``est`` against the ground-truth file ``gt`` in metres,
    None) or (None, why not)."""
    if gt is None:
        return None, "no ground truth"
    from dynastereo.eval import evaluate_files

    try:
        return float(evaluate_files(est, gt).ape["rmse"]), None
    except Exception as e:  # noqa: BLE001
        return None, f"{type(e).__name__}: {e}"


def generator_version() -> str:
    """Hash of the generator's sources: a cached sequence is regenerated when they change."""
    import dynastereo.synth as synth

    h = hashlib.sha1()
    for p in sorted(Path(synth.__file__).parent.glob("*.py")):
        h.update(p.read_bytes())
    return h.hexdigest()[:10]


def sequence(cache: Path, scenario: str, frames: int, seed: int, size: tuple[int, int]) -> tuple[Path, float | None]:
    """A synthetic sequence cached under ``cache``: (sequence folder, generation FPS or None
    when cached)."""
    from dynastereo.synth import generate

    root = cache / f"{scenario}_n{frames}_s{seed}_{size[0]}x{size[1]}_{generator_version()}"
    done = root / "done"
    if done.is_file():
        return root / "sequences" / "00", None
    shutil.rmtree(root, ignore_errors=True)
    t0 = time.perf_counter()
    seq = generate(root, scenario, frames=frames, seed=seed, size=size)
    fps = frames / (time.perf_counter() - t0)
    done.write_text("ok\n")
    return seq, fps


def old_tree(commit: str, dest: Path) -> Path:
    """``src`` of ``commit`` unpacked under ``dest`` (``git archive``)."""
    dest.mkdir(parents=True, exist_ok=True)
    arc = subprocess.run(["git", "-C", str(ROOT), "archive", commit, "src"], capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(dest)], input=arc.stdout, check=True)
    return dest / "src"


def head_commit() -> str:
    """This checkout's commit, ``+changes`` when its ``src`` differs from it."""
    git = ["git", "-C", str(ROOT)]
    head = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run([*git, "status", "--porcelain", "src"], capture_output=True, text=True).stdout.strip()
    return head + ("+changes" if dirty else "")


def score_raw_labels(run_dir: Path, labels_path: Path = RAW_LABELS) -> dict:
    """The motion test's verdicts in ``run_dir/objects.jsonl`` against the reference labels
    (``labels_path``): per reference object-frame (>= 300 px, labelled moving or static),
    the run's object matched by box IoU >= 0.5 (the best); right / undecided / wrong
    (an unmatched reference object is not counted); movers masked within 3 frames of
    their first appearance; static object-frames left unmasked."""
    from dynastereo.masking.boxes import box_iou

    lab = json.loads(labels_path.read_text())
    by_frame: dict[int, list] = {}
    for o in lab["objects"]:
        for f, box, px in zip(o["frames"], o["boxes"], o["pixels"]):
            by_frame.setdefault(int(f), []).append((o["id"], o["label"], o["moving"], box, px))
    counts = {"right": 0, "undecided": 0, "wrong": 0}
    per_label: dict[str, dict[str, int]] = {}
    masked_at: dict[int, list[int]] = {}
    static_frames = static_unmasked = 0
    for rec in (json.loads(s) for s in (run_dir / "objects.jsonl").read_text().splitlines() if s.strip()):
        f = int(rec["frame"])
        refs = by_frame.get(f, [])
        objs = rec["objects"]
        if not refs or not objs:
            continue
        iou = box_iou([r[3] for r in refs], [o["box"] for o in objs])
        for i, (rid, label, moving, box, px) in enumerate(refs):
            j = int(np.argmax(iou[i]))
            if iou[i, j] < 0.5:
                continue
            o = objs[j]
            if moving and o.get("masked", True):
                masked_at.setdefault(rid, []).append(f)
            if px < 300 or moving is None:
                continue
            v = o.get("moving")
            k = "undecided" if v is None else ("right" if bool(v) == bool(moving) else "wrong")
            counts[k] += 1
            per_label.setdefault(label, {"right": 0, "undecided": 0, "wrong": 0})[k] += 1
            if not moving:
                static_frames += 1
                static_unmasked += not o.get("masked", True)
    movers = [o for o in lab["objects"] if o["moving"] and max(o["pixels"]) >= 300]
    within = sum(1 for o in movers if any(f - o["frames"][0] <= 3 for f in masked_at.get(o["id"], [])))
    decided = counts["right"] + counts["wrong"]
    return {"object_frames": sum(counts.values()), **counts,
            "right_of_decided": counts["right"] / decided if decided else None,
            "movers": len(movers), "movers_masked_within_3": within,
            "static_frames": static_frames, "static_unmasked": static_unmasked, "by_label": per_label}
