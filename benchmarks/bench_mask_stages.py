"""Masking's CPU a stereo pair, stage by stage, the motion test's flow included.

What the masking thread of ``dynastereo run`` spends on a frame -- the detector
(``contrast`` + ``detect``), the carried boxes (``carry``), the boxes' ``disparity``,
``outline`` and ``transfer``, and the motion test's point flow (``motion_flow``) -- as
**process time** (all threads: a busy machine's other processes do not count, unlike wall
time), summed over every frame of a clip and divided by the frames (the network's runs
on every 2nd frame included), for each named setting (``--settings``: configuration
overrides over the defaults, below).  Each (clip, setting) runs in a subprocess of its
own (nothing shared: the compiled kernels, the network); the settings are alternated
inside each repeat, ``--repeats`` times; medians over the repeats.  The frames are decoded
before the clock runs (reading is not masking).  The masks' hash (left and right masks)
tells whether two settings give the same masks bit for bit.

Settings: ``default`` (the configuration's defaults), ``previous`` (the masking before
the cheap-masking search, explicit: ``stereo.scale 1``, ``detector.carry_downscale 1``),
``stereo2`` / ``carry2`` (one of them alone over ``previous``), ``band`` (``detector.band_top
0.25`` over the defaults), ``fast`` (``configs/fast.yaml``: ``stereo.scale 2`` and
``detector.carry_downscale 2``), ``band_carry2`` (the band and the half-size carrying), or
``key=value[;key=value...]``.  Clips: ``06``, ``03``,
``raw0001`` and the fast-motion variants of ``bench_peers.py`` (``06x2``, ``03x2``,
``06x3``, ``03x3``).

``--against OTHER/src`` runs another source tree beside this one's (``src``), alternated
with it inside each repeat (settings x trees), to compare code rather than settings; its
rows are named ``SETTING@against``.

Prints a table; writes ``benchmarks/results/mask_stages.json`` (``--out``).  Run:

    DYNASTEREO_DATA=... DYNASTEREO_MODELS=... .venv/bin/python benchmarks/bench_mask_stages.py \\
        [--clips 06,03,raw0001] [--settings previous,default] [--repeats 3] [--against ../main/src]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from _common import (FAST_VARIANTS, ROOT, clip_dirs, data_dir, fast_variant, load, machine, median, models_dir,
                     results_path, write_json)

OUT = results_path("mask_stages")
STAGES = ("contrast", "detect", "carry", "disparity", "outline", "transfer", "motion_flow")
SETTINGS = {
    "default": {},
    "previous": {"stereo.scale": 1, "detector.carry_downscale": 1},
    "stereo2": {"stereo.scale": 2, "detector.carry_downscale": 1},
    "carry2": {"stereo.scale": 1, "detector.carry_downscale": 2},
    "band": {"detector.band_top": 0.25},
    "fast": {"stereo.scale": 2, "detector.carry_downscale": 2},  # configs/fast.yaml
    "band_carry2": {"detector.band_top": 0.25, "detector.carry_downscale": 2},
}

# the child: one clip, one setting; prints one JSON line
CHILD = r"""
import hashlib, json, os, sys, time
from contextlib import contextmanager
from dynastereo.config import Config
from dynastereo.io import open_sequence
from dynastereo.masking import build_masker
from dynastereo.objects.motion import build_motion
from dynastereo.timing import StageTimer

class CpuTimer(StageTimer):
    @contextmanager
    def stage(self, name):
        c0 = time.process_time()
        try:
            yield
        finally:
            self.add(name, (time.process_time() - c0) * 1e3)

seq = open_sequence(sys.argv[1])
cfg = Config().with_overrides(json.loads(sys.argv[2]))
masker = build_masker(cfg, seq.calibration, models_dir=sys.argv[3])
motion = build_motion(cfg, seq.calibration, masker)
frames = [seq.frame(i) for i in range(len(seq))]
for f in frames:
    f.left_gray, f.right_gray  # decoded before the clock runs
masker.warm_up(*frames[0].left.shape[:2])
t, h = CpuTimer(), hashlib.sha1()
c0 = time.process_time()
for f in frames:
    t.start_frame(f.index)
    m = masker.mask(f, t)
    if motion is not None:
        with t.stage("motion_flow"):
            motion.measure(f, m)
    t.end_frame()
    h.update(m.left.tobytes()); h.update(m.right.tobytes())
total = (time.process_time() - c0) * 1e3 / len(frames)
n = len(frames)
stages = {k: sum(fr["ms"].get(k, 0.0) for fr in t.frames) / n for k in t.stage_names() if k != "total"}
print(json.dumps({"frames": n, "total_ms": total, "stages_ms": stages, "hash": h.hexdigest()[:16]}))
"""


def parse_setting(name: str) -> dict:
    if name in SETTINGS:
        return SETTINGS[name]
    out = {}
    for kv in name.split(";"):
        k, _, v = kv.partition("=")
        if not _:
            raise SystemExit(f"unknown setting {name!r}: one of {', '.join(SETTINGS)} or key=value[;key=value]")
        try:
            out[k.strip()] = json.loads(v)
        except ValueError:
            out[k.strip()] = v.strip()
    return out


def one(seq: Path, over: dict, models: Path, src: Path = ROOT / "src") -> dict:
    env = {**os.environ, "PYTHONPATH": str(src)}
    r = subprocess.run([sys.executable, "-c", CHILD, str(seq), json.dumps(over), str(models)], env=env,
                       capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"{seq} {over}: failed\n{r.stderr[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--clips", default="06,03,raw0001")
    ap.add_argument("--settings", default="previous,default")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--against", type=Path, default=None,
                    help="another tree's source folder, alternated with this one's (rows SETTING@against)")
    args = ap.parse_args()
    data, models = data_dir(), models_dir()
    tmp = tempfile.TemporaryDirectory(prefix="mask-stages-")
    clips = {}
    for c in [c.strip() for c in args.clips.split(",") if c.strip()]:
        if c in FAST_VARIANTS:
            base, step = FAST_VARIANTS[c]
            clips[c] = fast_variant(clip_dirs(data)[base], step, c, Path(tmp.name))
        elif c in clip_dirs(data):
            clips[c] = clip_dirs(data)[c]
        else:
            raise SystemExit(f"unknown clip {c!r}: of {', '.join([*clip_dirs(data), *FAST_VARIANTS])}")
    settings = {s: parse_setting(s) for s in [s.strip() for s in args.settings.split(",") if s.strip()]}
    trees = {"": ROOT / "src"}
    if args.against is not None:
        trees = {"@against": args.against.resolve(), **trees}
    rows = {s + t: (over, src) for s, over in settings.items() for t, src in trees.items()}
    runs: dict[str, dict[str, list[dict]]] = {c: {s: [] for s in rows} for c in clips}
    load_before = load()
    for rep in range(args.repeats):
        for c, seq in clips.items():
            for s, (over, src) in rows.items():
                r = one(seq, over, models, src)
                runs[c][s].append(r)
                print(f"[{rep + 1}/{args.repeats}] {c:8s} {s:24s} {r['total_ms']:6.1f} ms CPU a pair  "
                      + "  ".join(f"{k} {r['stages_ms'].get(k, 0.0):.1f}" for k in STAGES) + f"  [{r['hash']}]",
                      flush=True)
    tmp.cleanup()
    summary = {c: {s: {"total_ms": median([r["total_ms"] for r in rs], 2),
                       "masking_ms": median([sum(r["stages_ms"].get(k, 0.0) for k in STAGES) for r in rs], 2),
                       "stages_ms": {k: median([r["stages_ms"].get(k, 0.0) for r in rs], 2) for k in STAGES},
                       "hash": rs[0]["hash"], "frames": rs[0]["frames"]}
                   for s, rs in by.items()} for c, by in runs.items()}
    print(f"\nCPU ms a stereo pair (process time, medians of {args.repeats}; masking = the stages below)")
    print("| clip | setting | masking | " + " | ".join(STAGES) + " |")
    print("|---|---|---|" + "---|" * len(STAGES))
    for c, by in summary.items():
        for s, m in by.items():
            print(f"| {c} | {s} | **{m['masking_ms']:.1f}** | " + " | ".join(f"{m['stages_ms'][k]:.1f}" for k in STAGES)
                  + " |")
    doc = {"repeats": args.repeats, "machine": machine(load_before=load_before),
           "settings": settings, "summary": summary, "runs": runs}
    if args.against is not None:
        doc["against"] = str(args.against)
    write_json(args.out, doc)
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
