"""dynastereo.eval: trajectory files, APE/RPE/drift/KITTI metrics, report, plots.

Synthetic cases have known answers; the real-data cases use the official KITTI 06 poses.
"""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
from evo.core import metrics as evo_metrics
from evo.core.trajectory import PosePath3D
from evo.core.units import Unit

from conftest import require
from dynastereo.errors import InputError
from dynastereo.eval import (
    STAT_KEYS,
    Trajectory,
    TrajectoryWriter,
    evaluate,
    evaluate_files,
    format_table,
    kitti_odometry_error,
    plot_ape_over_time,
    plot_trajectories,
    read_trajectory,
    to_json_dict,
    write_kitti,
    write_tum,
)
from dynastereo.eval.metrics import drift
from dynastereo.eval.plot import top_view_plane

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


# --------------------------------------------------------------------------- helpers


def rot_y(theta: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations about y (KITTI camera: x right, y down, z forward)."""
    theta = np.atleast_1d(np.asarray(theta, dtype=np.float64))
    c, s = np.cos(theta), np.sin(theta)
    R = np.zeros((theta.size, 3, 3))
    R[:, 0, 0], R[:, 0, 2], R[:, 1, 1], R[:, 2, 0], R[:, 2, 2] = c, s, 1.0, -s, c
    return R


def drive(n: int, step: float = 1.0, yaw_rate: float | np.ndarray = 0.0, bump: float = 0.0) -> np.ndarray:
    """(n, 4, 4) camera-to-world poses of a car moving forward ``step`` m a frame,
    turning ``yaw_rate`` rad a frame; ``bump`` adds a vertical (y) wave of that amplitude."""
    yaw = np.concatenate([[0.0], np.cumsum(np.broadcast_to(yaw_rate, (n - 1,)))])
    R = rot_y(yaw)
    pos = np.concatenate([np.zeros((1, 3)), np.cumsum(step * R[:-1, :, 2], axis=0)])
    pos[:, 1] += bump * np.sin(np.arange(n) / 15.0)
    T = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    T[:, :3, :3], T[:, :3, 3] = R, pos
    return T


def curvy(n: int = 300) -> np.ndarray:
    """A non-degenerate 3D path (turns + vertical wave)."""
    return drive(n, 1.0, 0.02 * np.sin(np.arange(n - 1) / 40.0), bump=0.5)


def se3(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def perturb_increments(poses: np.ndarray, rng: np.random.Generator, sigma_t=0.02, sigma_r=0.0005) -> np.ndarray:
    """An odometry-like estimate: GT relative motions composed with small noise (drifts)."""
    rel = np.linalg.inv(poses[:-1]) @ poses[1:]
    yaw_noise = rot_y(rng.normal(0.0, sigma_r, rel.shape[0]))
    rel[:, :3, :3] = rel[:, :3, :3] @ yaw_noise
    rel[:, :3, 3] += rng.normal(0.0, sigma_t, (rel.shape[0], 3))
    out = [poses[0]]
    for r in rel:  # test helper only (sequential composition)
        out.append(out[-1] @ r)
    return np.array(out)


def devkit_reference(gt: np.ndarray, est: np.ndarray, lengths=(100, 200, 300, 400, 500, 600, 700, 800), step=10):
    """Line-by-line transcription of the KITTI devkit's calcSequenceErrors (evaluate_odometry.cpp)."""
    dist = [0.0]
    for i in range(1, len(gt)):
        dist.append(dist[-1] + float(np.linalg.norm(gt[i - 1, :3, 3] - gt[i, :3, 3])))
    t_errs, r_errs = [], []
    for first in range(0, len(gt), step):
        for length in lengths:
            last = next((i for i in range(first, len(dist)) if dist[i] > dist[first] + length), -1)
            if last == -1:
                continue
            d_gt = np.linalg.inv(gt[first]) @ gt[last]
            d_est = np.linalg.inv(est[first]) @ est[last]
            e = np.linalg.inv(d_est) @ d_gt
            d = 0.5 * (e[0, 0] + e[1, 1] + e[2, 2] - 1.0)
            r_errs.append(math.acos(max(min(d, 1.0), -1.0)) / length)
            t_errs.append(float(np.linalg.norm(e[:3, 3])) / length)
    if not t_errs:
        return None
    return 100.0 * np.mean(t_errs), 100.0 * 180.0 / math.pi * np.mean(r_errs), len(t_errs)


@pytest.fixture(scope="module")
def kitti06_poses(data_dir):
    return require(data_dir / "kitti_odometry/dataset/poses/06.txt", "KITTI ground-truth poses 06")


# --------------------------------------------------------------------------- APE / RPE known answers


def test_constant_offset_aligned_zero_unaligned_offset():
    gt = Trajectory(curvy(200), name="gt")
    offset = np.array([0.5, -0.2, 1.0])
    est_poses = gt.poses.copy()
    est_poses[:, :3, 3] += offset
    est = Trajectory(est_poses, name="est")

    aligned = evaluate(est, gt)
    assert aligned.ape["rmse"] < 1e-9 and aligned.ape["max"] < 1e-9
    assert np.allclose(aligned.alignment[:3, 3], -offset, atol=1e-9)
    assert aligned.warnings == []

    raw = evaluate(est, gt, align=False)
    norm = float(np.linalg.norm(offset))
    for k in ("max", "mean", "median", "min", "rmse"):
        assert raw.ape[k] == pytest.approx(norm, rel=1e-12)
    assert raw.ape["std"] == pytest.approx(0.0, abs=1e-12)
    assert raw.ape["sse"] == pytest.approx(200 * norm**2, rel=1e-12)
    assert np.allclose(raw.alignment, np.eye(4))
    # relative motion is identical: RPE 0, drift 0
    assert raw.rpe["max"] < 1e-9 and raw.rpe_rot_deg["max"] < 1e-6
    assert raw.drift_m < 1e-9


def test_identity_vs_offset_degenerate_path_still_aligns():
    """All-identity ground truth (a static camera): evo refuses the alignment, we fall back."""
    n = 20
    gt = Trajectory(np.broadcast_to(np.eye(4), (n, 4, 4)).copy())
    est_poses = gt.poses.copy()
    est_poses[:, :3, 3] = [0.3, 0.0, -0.4]
    est = Trajectory(est_poses)
    r = evaluate(est, gt)
    assert r.ape["rmse"] < 1e-12
    assert any("collinear or static" in w for w in r.warnings)
    assert r.drift_percent is None  # zero-length path
    raw = evaluate(est, gt, align=False)
    assert raw.ape["mean"] == pytest.approx(0.5, rel=1e-12)


def test_rigid_transform_gives_zero_ape_on_straight_and_curvy_paths():
    rng = np.random.default_rng(1)
    for poses in (curvy(250), drive(100)):  # drive(100): a straight, collinear path
        T = se3(random_rotation(rng), rng.normal(0, 50, 3))
        gt = Trajectory(poses)
        est = Trajectory(T @ poses)
        r = evaluate(est, gt)
        assert r.ape["rmse"] < 1e-8
        assert r.rpe["rmse"] < 1e-8  # RPE ignores a global transform
        assert np.allclose(r.estimate.positions, gt.positions, atol=1e-8)
        assert evaluate(est, gt, align=False).ape["rmse"] > 1.0
    # the curvy path determines the rotation: the alignment is T's inverse
    poses = curvy(250)
    T = se3(random_rotation(rng), [3.0, -2.0, 7.0])
    r = evaluate(Trajectory(T @ poses), Trajectory(poses))
    assert np.allclose(r.alignment, np.linalg.inv(T), atol=1e-9)


def test_isotropic_noise_gives_expected_rmse_and_mean():
    rng = np.random.default_rng(2)
    n, sigma = 4000, 0.1
    gt = Trajectory(drive(n, 0.5, 0.01 * np.sin(np.arange(n - 1) / 100.0), bump=2.0))
    est_poses = gt.poses.copy()
    est_poses[:, :3, 3] += rng.normal(0, sigma, (n, 3))
    r = evaluate(Trajectory(est_poses), gt)
    # |e| of a 3D isotropic Gaussian: E|e|^2 = 3 sigma^2, E|e| = 2 sigma sqrt(2/pi) (Maxwell)
    assert r.ape["rmse"] == pytest.approx(sigma * math.sqrt(3), rel=0.03)
    assert r.ape["mean"] == pytest.approx(2 * sigma * math.sqrt(2 / math.pi), rel=0.03)
    assert r.ape["sse"] == pytest.approx(n * r.ape["rmse"] ** 2, rel=1e-9)
    assert r.ape["min"] <= r.ape["median"] <= r.ape["max"]
    # consecutive-frame RPE: difference of two independent errors -> rmse sigma * sqrt(6)
    assert r.rpe["rmse"] == pytest.approx(sigma * math.sqrt(6), rel=0.03)
    assert len(r.ape_errors) == n


def test_rpe_delta_counts_pairs():
    gt = Trajectory(curvy(101))
    est = gt.poses.copy()
    est[:, :3, 3] *= 1.1  # 10 % scale error: RPE translation = 0.1 * step
    r1 = evaluate(Trajectory(est), gt, align=False, rpe_delta=1)
    r5 = evaluate(Trajectory(est), gt, align=False, rpe_delta=5)
    assert r1.rpe["median"] == pytest.approx(0.1, rel=0.01)
    assert r5.rpe["median"] == pytest.approx(0.5, rel=0.01)
    assert r5.rpe["sse"] / r5.rpe["rmse"] ** 2 == pytest.approx(20)  # 100 // 5 pairs


# --------------------------------------------------------------------------- drift


def test_drift_on_straight_path_known_final_error():
    n = 100  # 99 m straight along z
    gt = drive(n)
    est = gt.copy()
    est[:, 0, 3] += 0.02 * np.arange(n)  # lateral creep: 1.98 m at the end
    drift_m, length, pct = drift(est, gt)
    assert length == pytest.approx(99.0)
    assert drift_m == pytest.approx(1.98)
    assert pct == pytest.approx(2.0)
    # anchored at the first frame: a rigid transform of the whole estimate changes nothing
    T = se3(rot_y(0.7)[0], [10.0, 1.0, -5.0])
    r = evaluate(Trajectory(T @ est), Trajectory(gt))
    assert r.drift_percent == pytest.approx(2.0)
    assert r.path_length_m == pytest.approx(99.0)
    assert r.kitti is None  # 99 m < 100 m


# --------------------------------------------------------------------------- KITTI devkit metric


def test_kitti_metric_scale_error_gives_t_err():
    gt = drive(2401, 0.5)  # 1200 m straight
    est = gt.copy()
    est[:, :3, 3] *= 1.02
    k = kitti_odometry_error(est, gt)
    assert k is not None
    # each segment overshoots its length by < one step (0.5 m): t_err in [2 %, 2 % * 1.005]
    assert 2.0 <= k.t_err_percent <= 2.0 * 1.005
    assert k.r_err_deg_per_100m < 1e-5
    assert set(k.per_length) == {100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0}
    ref = devkit_reference(gt, est)
    assert k.t_err_percent == pytest.approx(ref[0], rel=1e-9) and k.n_segments == ref[2]


def test_kitti_metric_heading_bias_gives_r_err():
    gt = drive(2001, 0.5)  # 1000 m straight
    est = gt.copy()
    k_rad_per_m = 0.001
    est[:, :3, :3] = rot_y(k_rad_per_m * 0.5 * np.arange(2001))  # heading error grows with distance
    k = kitti_odometry_error(est, gt)
    assert k.r_err_deg_per_100m == pytest.approx(k_rad_per_m * 100 * 180 / math.pi, rel=0.006)


def test_kitti_metric_none_for_short_path():
    assert kitti_odometry_error(drive(100), drive(100)) is None  # 99 m
    assert kitti_odometry_error(drive(101), drive(101)) is None  # exactly 100 m: the devkit wants dist > 100
    assert kitti_odometry_error(drive(102), drive(102)) is not None  # 101 m: one segment
    assert kitti_odometry_error(drive(102), drive(102)).n_segments == 1


# --------------------------------------------------------------------------- files


def test_kitti_and_tum_round_trip(tmp_path):
    poses = curvy(57)
    ts = 1305031102.175304 + 0.1 * np.arange(57)
    write_kitti(tmp_path / "a.txt", poses)
    write_tum(tmp_path / "b.txt", poses, ts)
    a, b = read_trajectory(tmp_path / "a.txt"), read_trajectory(tmp_path / "b.txt")
    assert a.timestamps is None and len(a) == 57
    assert np.allclose(a.poses, poses, atol=1e-8)
    assert np.allclose(b.poses, poses, atol=1e-8)
    assert np.allclose(b.timestamps, ts, atol=1e-6, rtol=0)
    assert b.path == tmp_path / "b.txt" and a.name == "a"
    assert len((tmp_path / "b.txt").read_text().splitlines()[0].split()) == 8
    assert not list(tmp_path.glob(".*.tmp"))  # atomic writer leaves no temporary file


def test_reader_skips_comments_and_accepts_commas(tmp_path):
    p = tmp_path / "t.txt"
    p.write_text("# timestamp tx ty tz qx qy qz qw\n\n0.0,1,2,3,0,0,0,1\n0.1 1 2 4 0 0 0.7071068 0.7071068\n")
    t = read_trajectory(p)
    assert np.allclose(t.positions, [[1, 2, 3], [1, 2, 4]])
    assert np.allclose(t.poses[1, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-6)


@pytest.mark.parametrize(
    "text, expect",
    [
        ("1 0 0 0 0 1 0 0 0 0 1 0\n# comment\n1 0 0 0 0 1 0 0 0 0 1\n", "line 3: expected 12 numbers"),
        ("0 1 2 3 0 0 0 1\n0.1 1 2 x3 0 0 0 1\n", "line 2: 'x3' is not a number"),
        ("0 1 2 3 0 0 1\n", "line 1: expected 12 numbers (KITTI"),
        ("0 1 2 3 0 0 0 1\n0.1 nan 2 3 0 0 0 1\n", "line 2: non-finite"),
        ("0 1 2 3 0 0 0 0\n", "line 1: zero quaternion"),
        ("# nothing\n\n", "no poses"),
    ],
)
def test_malformed_file_error_names_file_and_line(tmp_path, text, expect):
    p = tmp_path / "broken_traj.txt"
    p.write_text(text)
    with pytest.raises(InputError) as e:
        read_trajectory(p)
    assert expect in str(e.value)
    assert "broken_traj.txt" in str(e.value) and e.value.path == p


def test_missing_file_is_input_error(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_trajectory(tmp_path / "nope.txt")


def test_trajectory_writer_keeps_rows_after_a_crash(tmp_path):
    poses = curvy(8)
    with pytest.raises(RuntimeError):
        with TrajectoryWriter(tmp_path) as w:
            for i, p in enumerate(poses[:5]):
                w.append(p, frame_index=2 * i, timestamp=0.1 * i)
                # flushed: readable while the writer is still open
                assert len(read_trajectory(w.kitti_path)) == i + 1
            raise RuntimeError("SLAM crashed")
    k = read_trajectory(tmp_path / "trajectory.kitti.txt")
    t = read_trajectory(tmp_path / "trajectory.tum.txt")
    assert np.allclose(k.poses, poses[:5], atol=1e-8) and np.allclose(t.poses, poses[:5], atol=1e-8)
    assert np.allclose(t.timestamps, 0.1 * np.arange(5))
    assert (tmp_path / "trajectory.frames.txt").read_text().split() == ["0", "2", "4", "6", "8"]
    with pytest.raises(ValueError):
        w.append(poses[5])  # closed


def test_frames_file_beside_estimate_maps_rows(tmp_path):
    gt = curvy(60)
    write_kitti(tmp_path / "gt.txt", gt)
    with TrajectoryWriter(tmp_path / "run") as w:
        for i in range(0, 60, 3):  # tracking kept every third frame
            w.append(gt[i], frame_index=i)
    r = evaluate_files(tmp_path / "run/trajectory.kitti.txt", tmp_path / "gt.txt")
    assert r.n_frames == 20 and r.ape["rmse"] < 1e-7
    assert "trajectory.frames.txt" in r.matching
    assert any("cut to the estimate's 20 frames" in w for w in r.warnings)
    # without the side file the rows would be matched 0..19: wrong
    assert evaluate_files(w.kitti_path, tmp_path / "gt.txt", use_frames_file=False).ape["rmse"] > 1.0


# --------------------------------------------------------------------------- matching


def test_longer_ground_truth_is_cut_with_warning():
    gt = Trajectory(curvy(300), name="gt")
    est = Trajectory(gt.poses[:120].copy())
    r = evaluate(est, gt)
    assert r.n_frames == 120 and r.ape["rmse"] < 1e-9
    assert len(r.warnings) == 1 and "300 poses; cut to the estimate's 120 frames" in r.warnings[0]
    assert r.path_length_m == pytest.approx(Trajectory(gt.poses[:120]).path_length)


def test_estimate_longer_than_ground_truth_is_an_error():
    with pytest.raises(InputError, match="estimate has 50 poses but the ground truth only 40"):
        evaluate(Trajectory(curvy(50)), Trajectory(curvy(40)))


def test_tum_association_by_timestamp():
    gt_poses = curvy(200)
    gt = Trajectory(gt_poses, timestamps=100.0 + 0.1 * np.arange(200))
    est = Trajectory(gt_poses[20:70], timestamps=100.0 + 0.1 * np.arange(20, 70) + 0.003)
    r = evaluate(est, gt)
    assert r.matching == "timestamp" and r.n_frames == 50 and r.ape["rmse"] < 1e-9
    assert any("cut to the 50 matching" in w for w in r.warnings)
    # a timestamped estimate against a KITTI ground truth (no timestamps): row i is frame i
    kitti_gt = Trajectory(gt_poses)
    r2 = evaluate(Trajectory(gt_poses[:50], timestamps=0.1 * np.arange(50)), kitti_gt)
    assert r2.matching == "frame index" and r2.ape["rmse"] < 1e-9
    far = Trajectory(gt_poses[:5], timestamps=500.0 + np.arange(5))
    with pytest.raises(InputError, match="no estimated pose has a ground-truth pose within"):
        evaluate(far, gt)


def test_frame_indices_with_revisits():
    gt = Trajectory(curvy(40))
    fi = list(range(0, 30)) + list(range(29, 9, -1))  # forward, then back over frames 29..10
    est = Trajectory(gt.poses[fi])
    r = evaluate(est, gt, frame_indices=fi)
    assert r.n_frames == 50 and r.ape["rmse"] < 1e-9
    assert r.path_length_m == pytest.approx(Trajectory(gt.poses[fi]).path_length)
    with pytest.raises(InputError, match="estimate has 50 poses"):  # row matching cannot work here
        evaluate(est, gt)
    with pytest.raises(InputError, match="frames 0..45 but the ground truth has 40"):
        evaluate(Trajectory(gt.poses[:3]), gt, frame_indices=[0, 1, 45])


# --------------------------------------------------------------------------- report


def test_table_and_json():
    rng = np.random.default_rng(3)
    gt = Trajectory(drive(2401, 0.5, 0.002 * np.sin(np.arange(2400) / 200.0)), name="gt")
    est = Trajectory(perturb_increments(gt.poses, rng), name="run1")
    r = evaluate(est, gt)
    table = format_table(r)
    header = next(ln for ln in table.splitlines() if "max(m)" in ln).split()
    assert header == ["max(m)", "mean(m)", "median(m)", "min(m)", "rmse(m)", "sse(m^2)", "std(m)"]
    ape_row = next(ln for ln in table.splitlines() if ln.startswith("APE run1")).split()[2:]
    assert [float(v) for v in ape_row] == pytest.approx([r.ape[k] for k in STAT_KEYS], rel=0.01)
    assert "KITTI devkit: t_err" in table and "drift:" in table

    d = to_json_dict(r)
    text = json.dumps(d, allow_nan=False)
    for k in STAT_KEYS:
        assert d[f"ape.{k}"] == r.ape[k] and d[f"rpe.{k}"] == r.rpe[k]
    assert d["drift_percent"] == r.drift_percent and d["n_frames"] == 2401
    assert d["kitti.t_err_percent"] == r.kitti.t_err_percent and d["kitti.r_err_deg_per_100m"] > 0
    assert json.loads(text)["path_length_m"] == pytest.approx(1200.0, rel=1e-3)

    short = evaluate(Trajectory(gt.poses[:50]), gt)
    ds = to_json_dict(short)
    assert ds["kitti.t_err_percent"] is None and ds["warnings"]
    assert "KITTI devkit: n/a" in format_table(short) and "warning: " in format_table(short)


# --------------------------------------------------------------------------- plots


def test_plots_are_valid_pngs(tmp_path):
    gt = Trajectory(curvy(200), name="gt")
    est_poses = gt.poses.copy()
    est_poses[:, :3, 3] += np.random.default_rng(4).normal(0, 0.3, (200, 3))
    r = evaluate(Trajectory(est_poses), gt)
    p = plot_trajectories(r.estimate, r.ground_truth, tmp_path / "sub/traj.png", "test")
    q = plot_ape_over_time(r, tmp_path / "ape.png")
    for f, shape in ((p, (600, 700, 3)), (q, (400, 800, 3))):
        assert f.read_bytes()[:8] == PNG_MAGIC
        img = cv2.imread(str(f))
        assert img is not None and img.shape == shape
        assert (img < 128).any()  # something dark (the lines) was drawn on white
    assert top_view_plane(gt) == "xz"  # KITTI camera: y (down) barely moves
    zup = gt.poses.copy()
    zup[:, :3, 3] = gt.positions[:, [0, 2, 1]]
    assert top_view_plane(Trajectory(zup)) == "xy"
    with pytest.raises(ValueError):
        plot_trajectories(gt, gt, tmp_path / "x.png", plane="xq")


# --------------------------------------------------------------------------- real data: KITTI 06


def test_kitti06_against_itself_and_perturbed(kitti06_poses, tmp_path):
    gt = read_trajectory(kitti06_poses)
    assert len(gt) == 1101
    assert np.allclose(gt.poses[0], np.eye(4), atol=1e-6)
    assert 1200.0 < gt.path_length < 1250.0  # KITTI 06 is about 1.2 km

    same = evaluate(gt, gt)
    assert same.ape["rmse"] < 1e-6 and same.drift_m < 1e-9
    assert same.kitti.t_err_percent < 1e-6 and same.kitti.r_err_deg_per_100m < 1e-3

    rng = np.random.default_rng(6)
    est = Trajectory(perturb_increments(gt.poses, rng), name="perturbed")
    r = evaluate(est, gt)
    assert 0.1 < r.ape["rmse"] < 100.0 and r.ape["min"] <= r.ape["median"] <= r.ape["max"]
    ref = devkit_reference(gt.poses, est.poses)
    assert r.kitti.t_err_percent == pytest.approx(ref[0], rel=1e-9)
    assert r.kitti.r_err_deg_per_100m == pytest.approx(ref[1], rel=1e-9)
    assert r.kitti.n_segments == ref[2]
    assert 0.1 < r.kitti.t_err_percent < 20.0
    # the vectorized rotation RPE equals evo's (so3_log per pair)
    evo_rot = evo_metrics.RPE(evo_metrics.PoseRelation.rotation_angle_deg, delta=1, delta_unit=Unit.frames)
    evo_rot.process_data((PosePath3D(poses_se3=list(gt.poses)), PosePath3D(poses_se3=list(est.poses))))
    evo_stats = evo_rot.get_all_statistics()
    for k in STAT_KEYS:
        assert r.rpe_rot_deg[k] == pytest.approx(evo_stats[k], rel=1e-6, abs=1e-9)
    assert r.rpe_rot_deg["max"] > 0.01
    # APE after alignment can only be smaller than without it
    assert r.ape["rmse"] <= evaluate(est, gt, align=False).ape["rmse"]


def test_kitti06_first_frames_file_round_trip(kitti06_poses, tmp_path):
    """The 51 frames shipped with sequence 06: about 60 m, GT cut with a warning, no KITTI metric."""
    gt = read_trajectory(kitti06_poses)
    rng = np.random.default_rng(7)
    est = perturb_increments(gt.poses[:51], rng, sigma_t=0.01)
    write_kitti(tmp_path / "trajectory.kitti.txt", est)
    r = evaluate_files(tmp_path / "trajectory.kitti.txt", kitti06_poses)
    assert r.n_frames == 51 and 50.0 < r.path_length_m < 70.0
    assert r.kitti is None
    assert any("1101 poses; cut to the estimate's 51 frames" in w for w in r.warnings)
    assert 0.0 < r.ape["rmse"] < 1.0 and r.drift_percent > 0.0
    png = plot_trajectories(r.estimate, r.ground_truth, tmp_path / "traj.png", "KITTI 06, frames 0-50")
    assert png.read_bytes()[:8] == PNG_MAGIC


def test_loss_budget_counts_known_errors():
    """An ellipse-shaped object in a 20 x 40 box: its outline covers it plus a 2-row strip of
    road at the box's bottom and 4 background pixels at the top; another box's mask takes 4
    background pixels; 12 object pixels are missed.  Pixels of a second GT object inside the
    box count as neither."""
    from types import SimpleNamespace

    from dynastereo.eval.masks import LossBudget

    h, w = 60, 80
    gt = np.zeros((h, w), np.uint8)
    cv2.ellipse(gt, (30, 30), (9, 19), 0, 0, 360, 5, -1)  # object 5 in box x 21..40, y 11..50
    box = (21, 11, 40, 50)
    gt[30:34, 21:24] = 7  # a piece of another object inside the box, masked by nobody
    labels = np.zeros((h, w), np.int32)
    labels[gt == 5] = 1
    labels[48:50, 21:40] = np.where(gt[48:50, 21:40] == 0, 1, labels[48:50, 21:40])  # road at the base
    labels[11, 21:25] = 1  # background at the top-left corner of the box
    labels[13, 21:25] = 2  # the other detection's mask over background
    missed = np.argwhere(gt == 5)[:12]
    labels[missed[:, 0], missed[:, 1]] = 0
    n_obj = int(np.count_nonzero(gt == 5))
    base_fp = int(np.count_nonzero((labels[48:50, 21:40] == 1) & (gt[48:50, 21:40] == 0)))
    assert base_fp > 0 and not gt[11, 21:25].any() and not gt[13, 21:25].any()

    obj = SimpleNamespace(id=5, box_left=box, distance=10.0, pixels_left=n_obj)
    far = SimpleNamespace(id=7, box_left=(21, 30, 24, 34), distance=45.0, pixels_left=12)  # beyond 30 m: not scored
    b = LossBudget()
    b.add([obj, far], [obj, far], [SimpleNamespace(method="outline"), SimpleNamespace(method="box")], labels, gt)
    s = b.summary()
    assert s["objects"] == 1 and s["outlined"] == 1 and s["fallbacks"] == 0
    assert s["object_pixels"] == n_obj
    assert s["fp_own"] == round((base_fp + 4) / n_obj, 4)
    assert s["fp_own_base"] == round(base_fp / n_obj, 4)
    assert s["fp_other"] == round(4 / n_obj, 4)
    assert s["missed"] == round(12 / n_obj, 4)
