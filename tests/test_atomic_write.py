"""io.outputs.atomic_open / atomic_write_text / atomic_write_bytes: the one atomic writer that
timing.json, trajectories, maps, vocabularies, point clouds and EuRoC ground truth use."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from dynastereo.io.outputs import atomic_open, atomic_write_bytes, atomic_write_text


def test_writes_text_and_bytes_with_open_s_permissions(tmp_path) -> None:
    p = atomic_write_text(tmp_path / "sub" / "a.txt", "héllo\n", fsync=False)
    assert p == tmp_path / "sub" / "a.txt" and p.read_text() == "héllo\n"
    q = atomic_write_bytes(tmp_path / "b.bin", b"\x00\x01", fsync=True)
    assert q.read_bytes() == b"\x00\x01"
    (tmp_path / "plain").write_bytes(b"")
    want = stat.S_IMODE((tmp_path / "plain").stat().st_mode)  # not mkstemp's 0600
    assert stat.S_IMODE(q.stat().st_mode) == want
    assert sorted(os.listdir(tmp_path)) == ["b.bin", "plain", "sub"]


def test_an_error_mid_write_keeps_the_old_file_and_leaves_nothing(tmp_path) -> None:
    p = tmp_path / "t.json"
    p.write_text("old")
    for exc in (OSError(28, "No space left on device"), KeyboardInterrupt()):
        with pytest.raises(type(exc)):
            with atomic_open(p, "w") as f:
                f.write("new, half")
                raise exc
        assert p.read_text() == "old" and sorted(os.listdir(tmp_path)) == ["t.json"]


def test_mkdir_false_does_not_create_the_folder(tmp_path) -> None:
    with pytest.raises(FileNotFoundError):
        atomic_write_text(tmp_path / "missing" / "a.txt", "x", mkdir=False)
    assert not (tmp_path / "missing").exists()
    with pytest.raises(ValueError, match="'a'"):
        with atomic_open(tmp_path / "x", "a"):
            pass


def test_savetxt_through_atomic_open_gives_the_same_bytes_as_to_a_path(tmp_path) -> None:
    table = np.array([[1.5e9, 0.1, -2.0, 3.25, 0.0, 0.0, 0.0, 1.0]])
    np.savetxt(tmp_path / "direct.txt", table, fmt="%.9f")
    with atomic_open(tmp_path / "atomic.txt", "w", fsync=False) as f:
        np.savetxt(f, table, fmt="%.9f")
    assert (tmp_path / "atomic.txt").read_bytes() == (tmp_path / "direct.txt").read_bytes()


def test_timing_json_is_written_atomically_without_creating_folders(tmp_path) -> None:
    import json

    from dynastereo.timing import StageTimer

    t = StageTimer()
    t.write(tmp_path / "timing.json", wall_s=1.0)
    assert json.loads((tmp_path / "timing.json").read_text())["wall_s"] == 1.0
    assert sorted(os.listdir(tmp_path)) == ["timing.json"]
    with pytest.raises(FileNotFoundError):
        t.write(tmp_path / "gone" / "timing.json")
