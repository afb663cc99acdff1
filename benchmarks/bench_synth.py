"""Benchmark the synthetic sequence generator: frames per second at 640x192 per scenario.

For every scenario: ``generate`` writes ``--frames`` frames (default 60) to a temporary
folder, ``--repeats`` times (default 3), with the default noise; reported are medians of

* ``fps``      frames / (wall time - set-up), set-up = building the city textures and the
               plan (measured with a 1-frame run), i.e. the steady rendering+writing rate;
* ``fps_all``  frames / wall time including the set-up;
* ``cpu_ms``   process CPU time per frame after the set-up (all threads), a load-independent cost;
* ``setup_s``  the 1-frame run.

``--threads 1`` renders the two views one after the other; the default (2) renders them
(and writes the PNGs) in worker threads.  Target: >= 20 fps at 640x192.
The machine is shared and noisy: compare medians, and ``cpu_ms`` across machines.

Prints a table; writes benchmarks/results/synth.json.
Run: .venv/bin/python benchmarks/bench_synth.py [--frames 60] [--repeats 3] [--threads 2]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import machine, results_path, write_json
from dynastereo.synth import SCENARIOS, generate

OUT = results_path("synth")
TARGET_FPS = 20.0


def run_once(scenario: str, frames: int, size: tuple[int, int], threads: int) -> tuple[float, float]:
    tmp = Path(tempfile.mkdtemp(prefix="bench_synth_"))
    try:
        t0 = time.perf_counter()
        c0 = time.process_time()
        generate(tmp, scenario, frames=frames, size=size, threads=threads)
        return time.perf_counter() - t0, time.process_time() - c0
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--size", default="640x192")
    ap.add_argument("--scenarios", default=",".join(SCENARIOS))
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    rows = []
    for sc in args.scenarios.split(","):
        setup = []
        setup_cpu = []
        wall = []
        cpu = []
        for _ in range(args.repeats):
            s_wall, s_cpu = run_once(sc, 1, (w, h), args.threads)
            f_wall, f_cpu = run_once(sc, args.frames, (w, h), args.threads)
            setup.append(s_wall)
            setup_cpu.append(s_cpu)
            wall.append(f_wall)
            cpu.append(f_cpu)
        setup_s = float(np.median(setup))
        cpu_frame = max(float(np.median(cpu)) - float(np.median(setup_cpu)), 0.0) / max(args.frames - 1, 1)
        wall_s = float(np.median(wall))
        steady = max(wall_s - setup_s, 1e-9) / max(args.frames - 1, 1)
        rows.append(
            {
                "scenario": sc,
                "frames": args.frames,
                "fps": round(1.0 / steady, 2),
                "fps_all": round(args.frames / wall_s, 2),
                "cpu_ms": round(cpu_frame * 1e3, 2),
                "setup_s": round(setup_s, 3),
                "wall_s": [round(v, 3) for v in wall],
                "meets_target": bool(1.0 / steady >= TARGET_FPS),
            }
        )
        r = rows[-1]
        print(f"{sc:10s} fps {r['fps']:7.2f}  fps_all {r['fps_all']:7.2f}  cpu/frame {r['cpu_ms']:7.2f} ms  setup {r['setup_s']:.2f} s", flush=True)
    print()
    print(f"{'scenario':10s} {'fps':>8s} {'fps_all':>8s} {'cpu_ms':>8s} {'setup_s':>8s}  target {TARGET_FPS:g} fps")
    for r in rows:
        print(f"{r['scenario']:10s} {r['fps']:8.2f} {r['fps_all']:8.2f} {r['cpu_ms']:8.2f} {r['setup_s']:8.2f}  {'ok' if r['meets_target'] else 'BELOW'}")
    result = {
        "benchmark": "synth",
        "size": [w, h],
        "frames": args.frames,
        "repeats": args.repeats,
        "threads": args.threads,
        "target_fps": TARGET_FPS,
        "machine": machine(),
        "results": rows,
    }
    write_json(OUT, result, indent=2)
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
