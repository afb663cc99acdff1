"""The fault suite's data-loss cases: nothing written earlier is lost.

* ``--overwrite`` checks every input and option (a truncated map, a text file as the
  vocabulary, a bad ``--gt`` with ``--report``, an unwritable ``--rrd``) before it clears
  anything, and clears only what the program wrote (its frame images in ``masks/`` and
  ``disparity/``; a user's own files there stay);
* ``export-bag --overwrite`` replaces the earlier bag only with a complete one;
* an output path that is also an input (``eval --plot EST``, ``report RUN --out
  RUN/trajectory.kitti.txt``), or a file of the input sequence's folder, is refused;
* a second job into an output folder in use is refused (the folder is locked).

Real KITTI 06 frames (4-frame copies); the SLAM without masks where a run is needed.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

from test_faults_inputs import assert_one_line, cli, mini06


def _digest(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` (relative path -> sha256): what must survive."""
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.name != ".dynastereo.lock"}


@pytest.fixture(scope="module")
def earlier(kitti06: Path, tmp_path_factory) -> tuple[Path, Path]:
    """(a 4-frame KITTI 06 copy, the output folder of a run of it with --save-masks)."""
    from dynastereo.api import run_sequence
    from dynastereo.config import Config

    root = tmp_path_factory.mktemp("earlier")
    seq = mini06(kitti06, root / "seq")
    out = root / "out"
    run_sequence(seq, out, Config().with_overrides({"masker.kind": "none"}), save_masks=True, stereo_check=False)
    assert (out / "trajectory.kitti.txt").is_file() and (out / "run.json").is_file()
    return seq, out


def _bad_map(tmp: Path) -> list[str]:
    p = tmp / "truncated.dsmap"
    p.write_bytes(b"PK\x03\x04" + b"\0" * 100)  # a zip's first bytes, then nothing
    return ["--load-map", str(p)]


def _text_vocabulary(tmp: Path) -> list[str]:
    p = tmp / "notes.txt"
    p.write_text("not a vocabulary\n")
    return ["--vocabulary", str(p)]


def _bad_gt(tmp: Path) -> list[str]:
    p = tmp / "gt.txt"
    p.write_text("1 2 3\n")
    return ["--gt", str(p), "--report"]


def _unwritable_rrd(tmp: Path) -> list[str]:
    return ["--rrd", "/proc/self/no/such/rec.rrd"]


BAD_INPUTS = {"truncated map": (_bad_map, "truncated.dsmap"), "text vocabulary": (_text_vocabulary, "notes.txt"),
              "bad --gt with --report": (_bad_gt, "gt.txt"), "unwritable --rrd": (_unwritable_rrd, "rec.rrd")}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_overwrite_checks_every_input_before_it_clears_the_earlier_run(case: str, earlier, tmp_path: Path) -> None:
    seq, out = earlier
    before = _digest(out)
    make, needle = BAD_INPUTS[case]
    r = cli(["run", seq, "--out", out, "--masker", "none", "--overwrite", *make(tmp_path)], tmp_path)
    assert_one_line(r, 2, needle)
    assert _digest(out) == before, "the earlier run was touched"


def test_overwrite_deletes_only_the_files_the_program_wrote(tmp_path: Path) -> None:
    from dynastereo.io.outputs import prepare_output_dir

    out = tmp_path / "out"
    own = ["masks/left/000000.png", "masks/right/000000.png", "disparity/000003.png", "overlays/000001.png",
           "objects.jsonl", "run.json"]
    users = ["masks/README.txt", "masks/left/mine.png", "masks/hand/000000.png", "disparity/ground_truth.png",
             "notes.md"]
    for name in own + users:
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_bytes(name.encode())
    prepare_output_dir(out, overwrite=True)
    assert [n for n in own if (out / n).exists()] == []
    assert [n for n in users if not (out / n).is_file()] == []
    assert (out / "masks/hand/000000.png").read_bytes() == b"masks/hand/000000.png"
    # a folder the program emptied goes; one with a user's file stays
    assert not (out / "overlays").exists() and (out / "masks/left").is_dir()


def test_export_bag_overwrite_keeps_the_earlier_bag_when_the_new_one_fails(kitti06: Path, tmp_path: Path) -> None:
    seq = mini06(kitti06, tmp_path / "seq")
    bag = tmp_path / "good.bag"
    assert cli(["export-bag", seq, bag, "--frames", 2], tmp_path).returncode == 0
    good = bag.read_bytes()
    broken = seq / "image_0" / "000002.png"
    broken.write_bytes(broken.read_bytes()[:300])  # frame 2 cannot be decoded: the export fails there
    r = cli(["export-bag", seq, bag, "--overwrite"], tmp_path)
    assert_one_line(r, 2, "000002.png")
    assert bag.read_bytes() == good, "the good bag was replaced by a partial one"
    assert not [p.name for p in tmp_path.iterdir() if p.name not in ("cache", "good.bag", "seq")]  # no temporary bag


def test_output_that_is_an_input_is_refused(earlier, tmp_path: Path) -> None:
    seq, out = earlier
    gt = tmp_path / "gt.txt"
    gt.write_bytes((out / "trajectory.kitti.txt").read_bytes())
    before = _digest(out)
    est = out / "trajectory.kitti.txt"
    assert_one_line(cli(["eval", est, gt, "--plot", est], tmp_path), 2, "--plot", "input")
    assert_one_line(cli(["eval", est, gt, "--plot", gt], tmp_path), 2, "--plot", "input")
    assert_one_line(cli(["report", out, "--out", est], tmp_path), 2, "--out", "input")
    assert_one_line(cli(["report", out, "--gt", gt, "--out", gt], tmp_path), 2, "--out", "input")
    assert _digest(out) == before and gt.read_bytes() == est.read_bytes()


def test_an_output_onto_a_file_of_the_input_sequence_is_refused(earlier, tmp_path: Path) -> None:
    """A file the command reads through its sequence folder (an image, the calibration, the
    stamps) is an input too: ``--save-cloud``, ``--save-map``, ``--rrd``, ``report --out``,
    ``gt --out`` and ``export-bag`` refuse it; a new file, or one in the run's own output
    folder inside the sequence, is written."""
    seq, out = earlier
    before = _digest(seq)
    image = sorted((seq / "image_0").iterdir())[0]
    run = ["run", seq, "--out", tmp_path / "run", "--masker", "none"]
    assert_one_line(cli([*run, "--save-cloud", image], tmp_path), 2, "--save-cloud", "input sequence")
    assert_one_line(cli([*run, "--save-map", seq / "times.txt"], tmp_path), 2, "--save-map", "input sequence")
    assert_one_line(cli([*run, "--rrd", seq / "calib.txt"], tmp_path), 2, "--rrd", "input sequence")
    assert_one_line(cli(["report", out, "--out", seq / "calib.txt"], tmp_path), 2, "--out", "input")
    assert_one_line(cli(["report", out, "--out", image], tmp_path), 2, "--out", "input sequence")
    assert_one_line(cli(["gt", seq, "--out", seq / "times.txt"], tmp_path), 2, "--out", "input")
    bag = seq / "old.bag"
    bag.write_bytes(b"not a bag")
    try:
        assert_one_line(cli(["export-bag", seq, bag, "--overwrite"], tmp_path), 2, "output bag", "input sequence")
    finally:
        bag.unlink()
    assert not (tmp_path / "run").exists()
    assert _digest(seq) == before, "a file of the input sequence was touched"
    inner = seq / "runs" / "a"
    try:  # the run's own folder inside the sequence: its files are outputs, written again
        for _ in range(2):
            r = cli(["run", seq, "--out", inner, "--masker", "none", "--overwrite", "--save-cloud", inner / "c.ply"],
                    tmp_path)
            assert r.returncode == 0, r.stderr
    finally:
        import shutil

        shutil.rmtree(seq / "runs")
    assert _digest(seq) == before


def test_an_output_onto_a_special_file_is_refused(earlier, tmp_path: Path) -> None:
    """Outputs are renamed into place when complete: onto a device or a FIFO that rename
    would replace the special file itself (as root, ``--save-mesh /dev/full`` left a
    regular file there).  Refused in one line; the special files stay what they were."""
    import os
    import stat

    seq, out = earlier
    fifo = tmp_path / "pipe.ply"
    os.mkfifo(fifo)
    run = ["run", seq, "--out", tmp_path / "run", "--masker", "none"]
    for flag, path in (("--save-mesh", fifo), ("--save-map", "/dev/null"), ("--rrd", "/dev/null"),
                       ("--save-cloud", fifo)):
        assert_one_line(cli([*run, flag, path], tmp_path), 2, flag, "special file")
    assert_one_line(cli(["report", out, "--out", "/dev/null"], tmp_path), 2, "special file")
    assert_one_line(cli(["eval", out / "trajectory.kitti.txt", out / "trajectory.kitti.txt", "--plot", fifo],
                        tmp_path), 2, "special file")
    assert stat.S_ISFIFO(fifo.stat().st_mode) and stat.S_ISCHR(os.stat("/dev/null").st_mode)


def test_a_second_job_into_a_folder_in_use_is_refused(earlier, tmp_path: Path) -> None:
    from dynastereo.api import run_sequence
    from dynastereo.config import Config
    from dynastereo.errors import OutputError
    from dynastereo.io.outputs import OutputLock

    seq, out = earlier
    before = _digest(out)
    with OutputLock(out):  # the first job holds the folder
        with pytest.raises(OutputError, match="in use by another dynastereo job"):
            OutputLock(out).acquire()
        with pytest.raises(OutputError, match="in use by another dynastereo job") as e:
            run_sequence(seq, out, Config().with_overrides({"masker.kind": "none"}), overwrite=True,
                         stereo_check=False)
        assert str(out) in str(e.value)
    assert _digest(out) == before
    # once it ended, the folder is free again
    run_sequence(seq, tmp_path / "other", Config().with_overrides({"masker.kind": "none"}), stereo_check=False)
    with OutputLock(out):
        pass


def test_the_api_refuses_an_earlier_run_by_default(earlier) -> None:
    from dynastereo.api import run_sequence
    from dynastereo.config import Config
    from dynastereo.errors import OutputError

    seq, out = earlier
    before = _digest(out)
    with pytest.raises(OutputError, match="earlier run"):
        run_sequence(seq, out, Config().with_overrides({"masker.kind": "none"}), stereo_check=False)
    assert _digest(out) == before
    assert json.loads((out / "run.json").read_text())["status"] == "done"


def test_synth_checks_its_options_before_it_clears_an_earlier_sequence(tmp_path: Path) -> None:
    out = tmp_path / "syn"
    assert cli(["synth", out, "--frames", 3, "--size", "64x32"], tmp_path).returncode == 0
    before = _digest(out)
    for bad, needle in ((["--scenario", "nope"], "unknown scenario"), (["--frames", 10**9], "--frames"),
                        (["--size", "100000x100000"], "--size")):
        assert_one_line(cli(["synth", out, "--overwrite", *bad], tmp_path), 2, needle)
        assert _digest(out) == before, bad


def test_gt_refuses_to_write_over_the_ground_truth_it_reads(kitti06: Path, tmp_path: Path) -> None:
    root = tmp_path / "k"
    seq = mini06(kitti06, root / "sequences" / "06")
    (root / "poses").mkdir()
    poses = root / "poses" / "06.txt"
    poses.write_bytes((kitti06.parents[1] / "poses" / "06.txt").read_bytes())
    before = poses.read_bytes()
    assert_one_line(cli(["gt", seq, "--out", poses, "--format", "kitti"], tmp_path), 2, "--out", "input")
    assert poses.read_bytes() == before
