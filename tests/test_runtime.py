"""The one runtime: every entry point through :func:`dynastereo.runtime.run` /
the one :class:`~dynastereo.runtime.loop.FrameLoop`, the job spec's validation, the stage
pipeline's hand-over, and the modes that must give the same results bit for bit --
prefetch on vs off, the live node pipelined vs serial -- with the default configuration
over all 51 frames of KITTI 06."""

from __future__ import annotations

import ast
import json
import threading
from pathlib import Path

import numpy as np
import pytest

from dynastereo.config import Config
from dynastereo.errors import ConfigError
from dynastereo.ros.bagrun import BagSource
from dynastereo.runtime import JobKind, JobSpec, OutputSpec, SourceSpec
from dynastereo.runtime.pipelining import StageFailed, StagePipeline

RUNTIME = Path(__file__).parents[1] / "src" / "dynastereo" / "runtime"


# --------------------------------------------------------------------------- the spec


@pytest.mark.parametrize("kw, match", [
    (lambda: dict(kind="run", source=SourceSpec(path="a", opener=BagSource("b.bag"))), "either a SEQUENCE"),
    (lambda: dict(kind="run", source=SourceSpec()), "either a SEQUENCE"),
    (lambda: dict(kind="run", source=SourceSpec(opener=BagSource("b.bag")), outputs=OutputSpec("o", save_map=Path("m"))),
     "--save-map / --load-map"),
    (lambda: dict(kind="run", source=SourceSpec(path="a"), localize_only=True), "--localize-only needs --load-map"),
    (lambda: dict(kind="mask", source=SourceSpec(path="a"), load_map=Path("m")), "a mask job tracks nothing: load_map"),
    (lambda: dict(kind="mask", source=SourceSpec(opener=BagSource("b.bag"))), "a mask job tracks nothing: bag"),
    (lambda: dict(kind="run", source=SourceSpec(path="a"), outputs=OutputSpec("o", overlays=True)), "dynastereo mask"),
    (lambda: dict(kind="nope", source=SourceSpec(path="a")), "nope"),
])
def test_job_spec_refuses_bad_combinations(kw, match) -> None:
    with pytest.raises((ConfigError, ValueError), match=match):
        JobSpec(**{"outputs": OutputSpec("o"), **kw()})


def test_source_and_bag_sources_check_their_options() -> None:
    with pytest.raises(ConfigError, match="--rate is for sequence folders"):
        SourceSpec(opener=BagSource("b.bag"), rate=10.0)
    with pytest.raises(ConfigError, match="--rate must be a frame rate in Hz"):
        SourceSpec(path="a", rate=0.0)
    with pytest.raises(ConfigError, match="--rate must be a frame rate in Hz"):
        SourceSpec(path="a", rate=1e-300)
    with pytest.raises(ConfigError, match="--sync-tolerance must be a time >= 0 ms"):
        BagSource("b.bag", tolerance_s=-0.001)
    with pytest.raises(ConfigError, match="--rectify"):
        BagSource("b.bag", rectify="maybe")
    assert BagSource("b.bag", outputs="odometry,tf").outputs == ("odometry", "tf")


def test_saving_the_disparity_makes_the_disparity_full_frame() -> None:
    spec = JobSpec(JobKind.MASK, SourceSpec(path="a"), OutputSpec("o", save_disparity=True))
    assert spec.config.stereo.region == "full" and Config().stereo.region != "full"


# --------------------------------------------------------------------------- the stage pipeline


class _Items:
    def __init__(self, n: int) -> None:
        self.items, self.lock = list(range(n)), threading.Lock()

    def take(self):
        with self.lock:
            return self.items.pop(0) if self.items else None


@pytest.mark.parametrize("pipelined", [False, True])
def test_pipeline_keeps_the_order_and_hands_errors_over(pipelined: bool) -> None:
    def stage(i: int) -> int:
        if i == 3:
            raise ValueError("bad frame 3")
        return i * 10

    pipe = StagePipeline(_Items(6).take, stage, pipelined=pipelined)
    got, failed = [], []
    while True:
        try:
            r = pipe.next()
        except StageFailed as f:
            failed.append((f.item, str(f.error)))
            continue
        if r is None:
            break
        got.append(r)
    assert got == [(0, 0), (1, 10), (2, 20), (4, 40), (5, 50)]
    assert failed == [(3, "bad frame 3")]
    assert pipe.close() and pipe.fallbacks == []


def test_pipeline_goes_serial_after_a_stuck_stage_and_records_it() -> None:
    release = threading.Event()

    def stage(i: int) -> int:
        if i == 1 and threading.current_thread().name == "dynastereo-mask":
            release.wait(20)  # stuck on the masking thread only
        return i

    pipe = StagePipeline(_Items(4).take, stage, pipelined=True, timeout_s=0.3)
    try:
        assert [pipe.next(k) for k in range(4)] == [(0, 0), (1, 1), (2, 2), (3, 3)]
        assert pipe.next() is None
    finally:
        release.set()
    assert [f["position"] for f in pipe.fallbacks] == [1] and not pipe.pipelined


def test_pipeline_waits_without_bound_for_a_quiet_source() -> None:
    """A live input may send nothing for long: only a stage that takes too long counts."""
    from dynastereo.io.queues import DropOldestQueue

    q = DropOldestQueue(2)
    pipe = StagePipeline(q.get, lambda i: i + 1, pipelined=True, timeout_s=0.2)
    threading.Timer(0.6, q.put, (7,)).start()
    assert pipe.next() == (7, 8) and pipe.fallbacks == []
    q.close()
    assert pipe.next() is None


def test_runtime_functions_stay_short() -> None:
    long = []
    for f in sorted(RUNTIME.glob("*.py")):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > 60:
                    long.append(f"{f.name}:{node.name} ({n} lines)")
    assert not long, f"functions over 60 lines in runtime/: {long}"


# --------------------------------------------------------------------------- every entry point, one runtime


class _Assembled(Exception):
    pass


def test_every_entry_point_runs_the_one_runtime(kitti06: Path, tmp_path: Path, monkeypatch) -> None:
    """mask, run, run --bag (API and CLI) and a bench job all reach runtime.job.assemble; the
    node's core runs the runtime's FrameLoop."""
    import dynastereo.api as api
    import dynastereo.runtime.job as job_mod
    from typer.testing import CliRunner

    from dynastereo.bench.discover import BenchSequence
    from dynastereo.bench.jobs import BenchJob, execute
    from dynastereo.cli.main import app
    from dynastereo.io import KittiSequence
    from dynastereo.ros.bags import export_bag
    from dynastereo.ros.core import StereoNodeCore
    from dynastereo.runtime.loop import FrameLoop

    bag = export_bag(KittiSequence(kitti06), tmp_path / "in.bag", "ros1", frames=[0, 1]).path
    seen: list[str] = []

    def assemble(spec, seq, observers, masker=None):
        seen.append(f"{spec.kind}:{spec.source.opener.kind if spec.source.opener else 'seq'}")
        raise _Assembled

    monkeypatch.setattr(job_mod, "assemble", assemble)
    calls = [
        lambda: api.mask_sequence(kitti06, tmp_path / "m", frames="0-1"),
        lambda: api.run_sequence(kitti06, tmp_path / "r", frames="0-1"),
        lambda: api.run_bag(bag, tmp_path / "b"),
        lambda: execute(BenchJob(BenchSequence("06", kitti06, "kitti", None), "none", 0, tmp_path / "j", {})),
    ]
    for call in calls:
        with pytest.raises(_Assembled):
            call()
    runner = CliRunner()
    for args in (["mask", str(kitti06), "-o", str(tmp_path / "cm")], ["run", str(kitti06), "-o", str(tmp_path / "cr")],
                 ["run", "--bag", str(bag), "-o", str(tmp_path / "cb")]):
        assert isinstance(runner.invoke(app, args).exception, _Assembled), args
    assert seen == ["mask:seq", "run:seq", "run:bag", "run:seq", "mask:seq", "run:seq", "run:bag"]
    core = StereoNodeCore(Config().with_overrides({"masker.kind": "none"}), calibration=KittiSequence(kitti06).calibration)
    assert isinstance(core.loop, FrameLoop) and core.loop.processor is core.processor
    core.shutdown()


def test_a_job_warms_its_masker_before_the_first_frame(kitti06: Path, tmp_path: Path) -> None:
    """The detector's first (lazily initialized) inference is made by the job's assembly, on
    a black frame of the sequence's size, before the frame loop -- not inside it."""
    from dynastereo.datatypes import StereoMasks
    from dynastereo.io import KittiSequence
    from dynastereo.runtime import run

    events: list[tuple] = []

    class _Masker:
        name = "counting"

        def warm_up(self, height: int, width: int) -> None:
            events.append(("warm", height, width))

        def mask(self, frame, timer=None):
            events.append(("mask", frame.index))
            return StereoMasks.empty(frame.shape)

    spec = JobSpec(JobKind.MASK, SourceSpec(path=kitti06), OutputSpec(tmp_path / "m"), Config(), frames="0-2")
    run(spec, masker=_Masker())
    c = KittiSequence(kitti06).calibration
    assert events == [("warm", c.height, c.width), ("mask", 0), ("mask", 1), ("mask", 2)]


def test_a_run_loads_the_slam_kernels_before_the_first_frame(kitti06: Path, tmp_path: Path, monkeypatch) -> None:
    """The SLAM's compiled kernels load on a background thread from the System's making;
    a run waits for them before its frame loop (start-up, not the loop: its FPS, a camera's
    first frames), and the System's ``wait_ready`` then returns at once."""
    from dynastereo.runtime import run
    from dynastereo.slam import system as slam_system
    from dynastereo.slam.local_mapping import BARunner

    events: list[str] = []
    loaded: list[bool] = []
    orig_wait, orig_track = slam_system.System.wait_ready, slam_system.System.track

    def wait_ready(self):
        events.append("wait")
        out = orig_wait(self)
        loaded.append(self.runner._ready.is_set())
        return out

    def track(self, frame, *a, **k):
        events.append(f"track {frame.index}")
        return orig_track(self, frame, *a, **k)

    monkeypatch.setattr(slam_system.System, "wait_ready", wait_ready)
    monkeypatch.setattr(slam_system.System, "track", track)
    spec = JobSpec(JobKind.RUN, SourceSpec(path=kitti06), OutputSpec(tmp_path / "r"),
                   Config().with_overrides({"masker.kind": "none"}), frames="0-1")
    run(spec)
    assert events == ["wait", "track 0", "track 1"] and loaded == [True]
    r = BARunner("thread", 1.0)
    assert r._ready is None and r.wait_warm_up() < 0.05  # never started: no wait
    r.warm_up()
    r.wait_warm_up()
    assert r._ready.is_set()


# --------------------------------------------------------------------------- bit for bit, all of KITTI 06


def _files(out: Path) -> dict[str, bytes]:
    names = ("trajectory.kitti.txt", "trajectory.tum.txt", "trajectory.frames.txt", "objects.jsonl",
             "objects_tracks.csv")
    got = {n: (out / n).read_bytes() for n in names}
    for side in ("left", "right"):
        for p in sorted((out / "masks" / side).glob("*.png")):
            got[f"masks/{side}/{p.name}"] = p.read_bytes()
    return got


def test_prefetch_on_and_off_give_the_same_run(kitti06: Path, models_dir: Path, tmp_path: Path) -> None:
    """The default configuration, all 51 frames: masking on the prefetch thread or inline,
    byte-identical trajectories, objects, tracks and masks."""
    from dynastereo.runtime import run

    outs = {}
    for prefetch in (True, False):
        out = tmp_path / f"prefetch_{prefetch}"
        spec = JobSpec(JobKind.RUN, SourceSpec(path=kitti06), OutputSpec(out, save_masks=True), Config(),
                       models_dir=models_dir, prefetch=prefetch)
        res = run(spec)
        assert len(res.frames) == 51
        outs[prefetch] = _files(out)
    assert len(outs[True]) == 5 + 2 * 51
    assert outs[True] == outs[False]


def test_features_ahead_and_the_mapping_thread_give_the_serial_run(kitti06: Path, tmp_path: Path) -> None:
    """``--masker none``, all 51 frames: features and stereo matches computed ahead on the
    prefetch thread and local mapping on its own thread, against everything on one
    thread (no prefetch, mapping inline) -- byte-identical trajectories."""
    from dynastereo.runtime import run

    outs = {}
    for threaded in (True, False):
        cfg = Config()
        cfg.masker.kind = "none"
        cfg.slam.local_mapping = "thread" if threaded else "inline"
        out = tmp_path / f"threaded_{threaded}"
        res = run(JobSpec(JobKind.RUN, SourceSpec(path=kitti06), OutputSpec(out), cfg, prefetch=threaded))
        assert len(res.frames) == 51 and res.stats["keyframes_created"] >= 10
        outs[threaded] = {n: (out / n).read_bytes() for n in ("trajectory.kitti.txt", "trajectory.frames.txt")}
        ms = json.loads((out / "timing.json").read_text())["frames"][5]["ms"]
        assert {"features", "stereo", "track"} <= set(ms)
    assert outs[True] == outs[False]


def test_live_node_pipelined_and_serial_give_the_same_poses(kitti06: Path, models_dir: Path) -> None:
    """The default configuration, all 51 frames fed one at a time (no drops): the node's
    two threads or one, the same poses and masks bit for bit."""
    from dynastereo.io import KittiSequence
    from dynastereo.ros.core import StereoInput, StereoNodeCore

    seq = KittiSequence(kitti06)
    stamps = seq.timestamps()
    runs = {}
    for pipelined in (False, True):
        core = StereoNodeCore(Config(), calibration=seq.calibration, models_dir=models_dir, pipelined=pipelined)
        masks: list[np.ndarray] = []
        core.sink = type("S", (), {"publish_pose": lambda s, r: masks.append(r.masks.left.copy()),
                                   "publish_images": lambda s, r, d: None, "wants_disparity": lambda s: False})()
        core.start()
        try:
            for i in range(len(seq)):
                f = seq.frame(i)
                core.submit(StereoInput(f.left, f.right, int(round(stamps[i] * 1e9))))
                assert core.wait_idle(120)
            poses, _ = core.trajectory()
            st = core.status()
        finally:
            core.shutdown()
        assert (st["processed"], st["dropped"], st["errors"]) == (51, 0, 0)
        runs[pipelined] = (poses, np.stack(masks))
    assert np.array_equal(runs[False][0], runs[True][0]) and np.array_equal(runs[False][1], runs[True][1])
    assert runs[False][1].any()  # something was masked: the comparison is not of empty masks
