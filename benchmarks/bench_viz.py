"""Benchmark what looking costs: the HTML report and the rerun recording.

On a synthetic ``convoy`` sequence (``--frames`` frames, default 40, 640x192, oracle
boxes, outline masks, masks saved), ``--repeats`` times (default 3), medians of

* ``report_s``      ``make_report`` on the run folder (evaluation, plots, 6 overlays);
* ``report_kib``    the size of the self-contained page;
* ``run_ms``        end-to-end ms per frame of the run without a viewer;
* ``rrd_ms``        the same run with ``rrd=FILE`` (every entity of ``viz/rerun.py``);
* ``rrd_extra_ms``  ``rrd_ms - run_ms`` (the recording's cost per frame; includes
                    rerun's import once, spread over the frames);
* ``rrd_kib_per_frame``  the recording's size per frame.

The machine is shared and noisy: compare medians.
Prints a table; writes benchmarks/results/viz.json.
Run: .venv/bin/python benchmarks/bench_viz.py [--frames 40] [--repeats 3]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import machine, results_path, write_json
from dynastereo.api import make_report, run_sequence
from dynastereo.config import Config
from dynastereo.synth import generate

OUT = results_path("viz")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_viz_"))
    try:
        seq = generate(tmp / "synth", "convoy", frames=a.frames, seed=0, size=(640, 192))
        cfg = Config().with_overrides({"detector.name": "oracle", "masker.kind": "outline"})
        rows: dict[str, list[float]] = {k: [] for k in ("report_s", "report_kib", "run_ms", "rrd_ms", "rrd_kib_per_frame")}
        for r in range(a.repeats):
            t0 = time.perf_counter()
            run_sequence(seq, tmp / "run", cfg, save_masks=True, overwrite=True)
            rows["run_ms"].append((time.perf_counter() - t0) * 1000 / a.frames)
            t0 = time.perf_counter()
            page = make_report(tmp / "run")
            rows["report_s"].append(time.perf_counter() - t0)
            rows["report_kib"].append(page.stat().st_size / 1024)
            rrd = tmp / f"run{r}.rrd"
            t0 = time.perf_counter()
            run_sequence(seq, tmp / "run_rrd", cfg, save_masks=True, rrd=rrd, overwrite=True)
            rows["rrd_ms"].append((time.perf_counter() - t0) * 1000 / a.frames)
            rows["rrd_kib_per_frame"].append(rrd.stat().st_size / 1024 / a.frames)
        med = {k: round(float(np.median(v)), 3) for k, v in rows.items()}
        med["rrd_extra_ms"] = round(med["rrd_ms"] - med["run_ms"], 3)
        for k, v in med.items():
            print(f"{k:20s} {v:10.3f}")
        write_json(OUT, {"frames": a.frames, "repeats": a.repeats, "size": [640, 192], "median": med,
                         "runs": rows, "machine": machine()})
        print(f"wrote {OUT}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
