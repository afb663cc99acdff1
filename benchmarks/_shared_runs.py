"""Runs and their evaluation, shared by several benchmarks: ``dynastereo run`` in its own
process (:func:`run_dynastereo`), a trajectory's ATE and drift (:func:`ate_drift`,
:func:`ate`) and the cached synthetic sequences (:func:`sequence`)."""

from __future__ import annotations

import hashlib
import shutil
import subprocess
import sys
import time
from pathlib import Path


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
