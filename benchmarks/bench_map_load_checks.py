"""What the map file's load-time checks cost: ``load_map`` of a map the size of a long run
(``_shared_maps.synthetic_map``: 100 keyframes x 2000 keypoints, 50 000 points) with the
code before and after (the observation lists' structure, finite points, every entry's
inflated size against the header's counts), alternated, each in its own process; the
median load time of each.

    python benchmarks/bench_map_load_checks.py --before /work/main/src [--after src] [--repeats 9]

Writes benchmarks/results/map_load_checks.json.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from _common import ROOT, machine, median, results_path, write_json
from _shared_maps import synthetic_map

OUT = results_path("map_load_checks")
CHILD = (
    "import sys, time\n"
    "from dynastereo.slam.map_io import load_map\n"
    "load_map(sys.argv[1])  # warm: imports, page cache\n"
    "t = []\n"
    "for _ in range(int(sys.argv[2])):\n"
    "    t0 = time.perf_counter(); load_map(sys.argv[1]); t.append((time.perf_counter() - t0) * 1e3)\n"
    "print(' '.join(f'{x:.3f}' for x in t))\n"
)


def load_ms(src: str, path: Path, n: int) -> list[float]:
    env = dict(os.environ, PYTHONPATH=str(Path(src).resolve()))
    r = subprocess.run([sys.executable, "-c", CHILD, str(path), str(n)], env=env, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"{src}: {r.stderr[-2000:]}")
    return [float(x) for x in r.stdout.split()]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", required=True, help="src folder of the code before (PYTHONPATH)")
    ap.add_argument("--after", default=str(ROOT / "src"), help="src folder of the code after")
    ap.add_argument("--repeats", type=int, default=9, help="loads per process")
    ap.add_argument("--rounds", type=int, default=3, help="processes per side, alternated")
    a = ap.parse_args()
    from dynastereo.slam.map_io import save_map

    ms: dict[str, list[float]] = {"before": [], "after": []}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "synthetic-100kf.dsmap"
        save_map(path, synthetic_map())
        for k in range(a.rounds):
            for name in (("before", "after") if k % 2 == 0 else ("after", "before")):
                ms[name] += load_ms(a.before if name == "before" else a.after, path, a.repeats)
        size = path.stat().st_size
    med = {k: median(v) for k, v in ms.items()}
    print(f"load_map, synthetic-100kf ({size / 2**20:.1f} MiB), median of {len(ms['after'])} loads: "
          f"before {med['before']:.1f} ms, after {med['after']:.1f} ms ({100 * (med['after'] / med['before'] - 1):+.1f} %)")
    res = {"map": "synthetic-100kf", "file_bytes": size, "loads": {k: len(v) for k, v in ms.items()},
           "ms": ms, "median_ms": med, "machine": machine(),
           "note": "a shared machine: medians of alternated processes"}
    write_json(OUT, res)
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
