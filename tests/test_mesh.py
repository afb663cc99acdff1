"""The dense, mover-free mesh (``dynastereo.mesh``, ``run --save-mesh``).

Known answers on stereo pairs made here (a textured road plane, a fronto-parallel box
that drives across it): the planar street gives a planar mesh; a masked mover leaves
nothing where it drove, an unmasked one does.  A whole run writes a PLY that another
reader (plyfile) loads with the vertex count the log and run.json state.  Bad settings
are refused with one line naming the key.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from dynastereo.config import Config, load_config
from dynastereo.datatypes import StereoCalibration
from dynastereo.errors import ConfigError
from dynastereo.mesh import KeyframeRecorder, KeyframeView, Mesh, TSDFVolume, fuse, read_ply, write_cloud_ply, write_mesh_ply
from dynastereo.mesh.render import render_camera, render_top
from dynastereo.mesh.tables import EDGES, TRIS

W, H, F, CX, CY, BASE, HEIGHT = 400, 128, 360.0, 200.0, 24.0, 0.54, 1.5
CALIB = StereoCalibration(np.array([[F, 0, CX], [0, F, CY], [0, 0, 1]]), BASE, W, H)
BOX_Z, BOX_W, BOX_TOP = 8.0, 1.6, -0.2  # the mover: a fronto-parallel board 8 m ahead, 1.6 m wide, from the road up


def _texture(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.uniform(0, 255, (H, 2 * W)).astype(np.float32), (0, 0), 1.2)
    return cv2.normalize(t, None, 20, 235, cv2.NORM_MINMAX)


def _pair(seed: int, box_x: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Left, right and the mover's left mask: a road plane HEIGHT below the camera (its
    disparity BASE * (v - CY) / HEIGHT per row), and the board at ``box_x`` (its centre, m)
    with a texture of its own.  The right image's pixel x shows what the left's x + d shows."""
    tex = _texture(seed)
    road_tex, board_tex = tex[:, :W + 64], tex[:, W:]
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    d_road = np.where(v > CY, BASE * (v - CY) / HEIGHT, 0.0).astype(np.float32)
    left = road_tex[:, :W].copy()
    mask = np.zeros((H, W), np.uint8)
    right = cv2.remap(road_tex, u + d_road, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    if box_x is not None:
        d_box = F * BASE / BOX_Z
        x0, x1 = F * (box_x - BOX_W / 2) / BOX_Z + CX, F * (box_x + BOX_W / 2) / BOX_Z + CX
        y0, y1 = F * BOX_TOP / BOX_Z + CY, F * HEIGHT / BOX_Z + CY
        inside = (u >= x0) & (u < x1) & (v >= y0) & (v < y1)
        left = np.where(inside, board_tex[:, :W], left)
        mask[inside] = 255
        seen = (u + d_box >= x0) & (u + d_box < x1) & (v >= y0) & (v < y1)
        board = cv2.remap(board_tex, u + d_box, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        right = np.where(seen, board, right)
    return left.astype(np.uint8), right.astype(np.uint8), mask


def _cfg(**mesh) -> Config:
    return Config().with_overrides({f"mesh.{k}": v for k, v in {"max_depth": 12.0, **mesh}.items()})


def test_marching_cubes_table_is_closed_and_consistent():
    """Every case's triangles use only edges whose corners differ in sign; each edge is used
    an even number of times around the case's loops (closed surfaces); the complement of a
    case without an ambiguous face is the same triangles turned over."""
    for case in range(256):
        tris = TRIS[case][TRIS[case] >= 0]
        assert len(tris) % 3 == 0
        for e in tris:
            a, b = EDGES[e]
            assert ((case >> a) & 1) != ((case >> b) & 1)
    assert (TRIS[0] < 0).all() and (TRIS[255] < 0).all()
    assert sorted(TRIS[1][:3]) == sorted(TRIS[254][:3])


def test_planar_street_gives_a_planar_mesh():
    """A road plane seen from a camera driving forward (0.8 m a keyframe): every vertex lies
    within one voxel of the plane, the median far closer; the surface covers the road."""
    cfg = _cfg()
    rec = KeyframeRecorder()
    poses = []
    for k in range(5):
        left, right, _ = _pair(k)
        rec.views.append(KeyframeView(k, left, right, None))
        P = np.eye(4)[:3]
        P[2, 3] = 0.8 * k
        poses.append(P)
    res = fuse(rec, np.array(poses), CALIB, cfg)
    V = res.mesh.vertices
    assert res.stats.keyframes == 5 and len(V) > 2000
    off = np.abs(V[:, 1] - HEIGHT)
    assert off.max() <= cfg.mesh.voxel_size
    assert np.median(off) <= 0.03
    # the road from the image's bottom row (5.2 m) to max_depth past the last keyframe, +-2 m across at least
    assert V[:, 2].min() < 6.0 and V[:, 2].max() > 14.0 and V[:, 0].min() < -2.0 and V[:, 0].max() > 2.0
    # triangles face the camera (up: -y)
    F_ = res.mesh.faces
    n = np.cross(V[F_[:, 1]] - V[F_[:, 0]], V[F_[:, 2]] - V[F_[:, 0]])
    assert np.mean(n[:, 1] < 0) > 0.99


def _mover_run(masked: bool) -> tuple[Mesh, list[float]]:
    """A static camera; the board drives across, 8 m ahead, one keyframe per position."""
    rec = KeyframeRecorder()
    xs = [-3.0, -1.5, 0.0, 1.5, 3.0]
    for k, x in enumerate(xs):
        left, right, mask = _pair(10 + k, x)
        rec.views.append(KeyframeView(k, left, right, mask))
    poses = np.repeat(np.eye(4)[None, :3], len(xs), axis=0)
    return fuse(rec, poses, CALIB, _cfg(), masked=masked).mesh, xs


def _near_board(V: np.ndarray, xs: list[float]) -> np.ndarray:
    """Vertices on the board's path: within 0.3 m of its face at any of its positions,
    above the road (a road vertex is not the board)."""
    near = np.zeros(len(V), bool)
    for x in xs:
        near |= ((np.abs(V[:, 2] - BOX_Z) < 0.3) & (np.abs(V[:, 0] - x) < BOX_W / 2 + 0.3)
                 & (V[:, 1] < HEIGHT - 0.25) & (V[:, 1] > BOX_TOP - 0.3))
    return near


def test_masked_mover_leaves_nothing_where_it_drove():
    masked, xs = _mover_run(True)
    unmasked, _ = _mover_run(False)
    assert len(masked.vertices) > 1000  # the road is there
    n_masked = int(_near_board(masked.vertices, xs).sum())
    n_unmasked = int(_near_board(unmasked.vertices, xs).sum())
    assert n_unmasked > 100, n_unmasked  # the board, fused unmasked, is in the mesh
    assert n_masked == 0, n_masked
    # the road behind the board's path is still seen (between its positions and after)
    road = (np.abs(masked.vertices[:, 1] - HEIGHT) < 0.1) & (masked.vertices[:, 2] > BOX_Z + 1)
    assert road.sum() > 200


def test_compare_fuses_both_from_one_disparity():
    """``compare``: the masked mesh and, beside it, the same keyframes fused without masks --
    each the same as its own fusion."""
    rec = KeyframeRecorder()
    for k, x in enumerate([-1.5, 1.5]):
        left, right, mask = _pair(20 + k, x)
        rec.views.append(KeyframeView(k, left, right, mask))
    poses = np.repeat(np.eye(4)[None, :3], 2, axis=0)
    both = fuse(rec, poses, CALIB, _cfg(), compare=True)
    alone = fuse(rec, poses, CALIB, _cfg())
    plain = fuse(rec, poses, CALIB, _cfg(), masked=False)
    np.testing.assert_array_equal(both.mesh.vertices, alone.mesh.vertices)
    np.testing.assert_array_equal(both.unmasked.vertices, plain.mesh.vertices)
    assert len(both.unmasked.vertices) > len(both.mesh.vertices) and alone.unmasked is None


def test_a_track_judged_moving_later_is_left_out_of_earlier_keyframes():
    """The recorder keeps a keyframe's instance labels; an object whose track turns moving
    at a later frame is left out of it too (its first frames' verdict was 'still')."""
    from dynastereo.datatypes import ObjectMask, StereoMasks

    labels = np.zeros((4, 6), np.int32)
    labels[1:3, 1:3] = 1
    still = ObjectMask((1, 1, 3, 3), "car", 0.9, "outline", 5.0, 4, 4, track_id=7, moving=False)
    m = StereoMasks(np.zeros((4, 6), np.uint8), np.zeros((4, 6), np.uint8), [still], labels_left=labels)
    rec = KeyframeRecorder()
    img = np.zeros((4, 6), np.uint8)
    rec.add(0, img, img, m, m, keyframe=True)
    assert rec.leave_out(rec.views[0]) is m.left or not rec.leave_out(rec.views[0]).any()
    later = ObjectMask((1, 1, 3, 3), "car", 0.9, "outline", 5.0, 4, 4, track_id=7, moving=True)
    rec.add(1, img, img, StereoMasks(m.left, m.right, [later]), None, keyframe=False)
    out = rec.leave_out(rec.views[0])
    assert (out[labels == 1] == 255).all() and (out[labels == 0] == 0).all()


def test_a_movers_disparity_bled_beyond_its_mask_is_left_out_and_the_background_kept():
    """The matcher smears a mover's disparity over the background beside it, further than
    ``mask_margin``: ``bleed_margin`` leaves out the pixels there at the mover's depth (a
    ghost at its depth otherwise) and keeps the background's own depth behind."""
    from dynastereo.mesh.fusion import depth_and_movers

    class Matcher:  # the background at 10 px, the mover (columns 200-239) at 40 px, bled 14 px to its right
        cfg = type("C", (), {"num_disparities": 16})()

        def compute(self, left, right):
            d = np.full(left.shape, 10.0, np.float32)
            d[:, 200:254] = 40.0
            return d

    mask = np.zeros((H, W), np.uint8)
    mask[:, 200:240] = 255
    view = KeyframeView(0, np.zeros((H, W), np.uint8), np.zeros((H, W), np.uint8), mask)
    kept = {}
    for bleed in (0, 24):
        z, movers = depth_and_movers(view, mask, CALIB, Matcher(), _cfg(scale=1, bleed_margin=bleed, max_depth=30.0).mesh)
        z[movers] = 0.0
        kept[bleed] = z
    bled = slice(249, 252)  # beyond the 8-px margin, off the disparity edge at 254
    assert (kept[0][:, bled] > 0).all()  # without the ring: the mover's depth, beside it -- a ghost
    assert not (kept[24][:, bled] > 0).any()
    assert (kept[24][:, 260:] > 0).all() and np.allclose(kept[24][:, 260:], CALIB.bf / 10.0)  # the background stays
    assert (kept[24][:, 20:190] > 0).all()


def test_ply_files_read_back_with_another_reader(tmp_path: Path):
    plyfile = pytest.importorskip("plyfile")
    vol = TSDFVolume(0.1, 0.3, 1)
    v, u = np.mgrid[0:H, 0:W]
    depth = np.where(v > CY, F * HEIGHT / np.maximum(v - CY, 1e-6), 0).astype(np.float32)
    depth[(depth > 15)] = 0
    img = np.dstack([np.full((H, W), c, np.uint8) for c in (10, 120, 250)])  # BGR
    vol.integrate(depth, img, CALIB.K, np.eye(4)[:3])
    vol.integrate(depth, img, CALIB.K, np.eye(4)[:3])
    mesh = vol.mesh()
    assert len(mesh.faces) > 100
    write_mesh_ply(tmp_path / "m.ply", mesh)
    write_cloud_ply(tmp_path / "c.ply", mesh)
    ply = plyfile.PlyData.read(str(tmp_path / "m.ply"))
    assert ply["vertex"].count == len(mesh.vertices) and ply["face"].count == len(mesh.faces)
    xyz = np.stack([ply["vertex"][k] for k in "xyz"], 1)
    np.testing.assert_allclose(xyz, mesh.vertices)
    faces = np.stack(ply["face"]["vertex_indices"])
    np.testing.assert_array_equal(faces, mesh.faces)
    # colour: BGR in, RGB in the file
    assert ply["vertex"]["red"].min() >= 248 and ply["vertex"]["blue"].max() <= 12
    cloud = plyfile.PlyData.read(str(tmp_path / "c.ply"))
    assert cloud["vertex"].count == len(mesh.vertices) and "face" not in [e.name for e in cloud.elements]
    back = read_ply(tmp_path / "m.ply")
    np.testing.assert_array_equal(back.faces, mesh.faces)


def test_pictures_show_the_mesh():
    vol = TSDFVolume(0.1, 0.3, 1)
    v, _ = np.mgrid[0:H, 0:W]
    depth = np.where(v > CY, F * HEIGHT / np.maximum(v - CY, 1e-6), 0).astype(np.float32)
    depth[depth > 15] = 0
    for _ in range(2):
        vol.integrate(depth, np.full((H, W), 200, np.uint8), CALIB.K, np.eye(4)[:3])
    mesh = vol.mesh()
    top = render_top(mesh, (200, 300))
    cam = render_camera(mesh, CALIB.K, (W, H))
    assert top.shape == (300, 200, 3) and cam.shape == (H, W, 3)
    assert (top.sum(-1) != 120).mean() > 0.1  # not the background alone (a wedge of road)
    # from the camera: the road from 15 m (row CY + F * HEIGHT / 15) down, nothing above the horizon
    lit = cam.sum(-1) != 120
    near = int(CY + F * HEIGHT / 15) + 2
    assert lit[near:H - 10].mean() > 0.9 and lit[: int(CY) - 2].mean() == 0


def test_a_volume_over_its_memory_budget_stops_in_one_line():
    """The voxel grid grows up to its budget, never past it: a depth map that needs more
    blocks stops with one line that says which settings to change."""
    from dynastereo.errors import DynastereoError
    from dynastereo.mesh.tsdf import BLOCK_BYTES

    depth = np.full((H, W), 8.0, np.float32)
    img = np.full((H, W), 128, np.uint8)
    small = TSDFVolume(0.1, 0.3, 1, max_bytes=50 * BLOCK_BYTES)  # 50 blocks
    with pytest.raises(DynastereoError) as e:
        small.integrate(depth, img, CALIB.K, np.eye(4)[:3])
    assert "mesh.voxel_size" in str(e.value) and "\n" not in str(e.value)
    assert small.nbytes <= 50 * BLOCK_BYTES
    ok = TSDFVolume(0.1, 0.3, 1)
    ok.integrate(depth, img, CALIB.K, np.eye(4)[:3])
    assert 50 < ok.n_blocks and ok.nbytes <= ok.max_bytes


@pytest.mark.parametrize("key,value,words", [
    ("voxel_size", 0, "mesh.voxel_size must be > 0 m"),
    ("voxel_size", -0.1, "mesh.voxel_size must be > 0 m"),
    ("truncation", 0.05, "mesh.truncation must be at least one voxel"),
    ("truncation", 5, "at most 32"),  # 50 voxels: blocks far before and behind every surface
    ("voxel_size", 0.001, "at least 0.01 m"),  # the grid's memory grows as 1 / voxel^2
    ("max_depth", 0.5, "mesh.min_depth and mesh.max_depth"),
    ("scale", 3, "mesh.scale must be one of"),
    ("bleed_margin", -1, "mesh.bleed_margin must be in [0, 128] px"),
])
def test_bad_settings_are_refused_in_one_line(key, value, words, tmp_path: Path):
    with pytest.raises(ConfigError) as e:
        Config().with_overrides({f"mesh.{key}": value})
    assert words in str(e.value) and "\n" not in str(e.value)
    path = tmp_path / "bad.yaml"
    path.write_text(f"mesh:\n  {key}: {value}\n")
    with pytest.raises(ConfigError) as e:
        load_config(path)
    assert words in str(e.value) and str(path) in str(e.value) and "\n" not in str(e.value)


def test_a_mesh_over_its_budget_fails_the_run_in_one_line_and_keeps_its_files(tmp_path: Path, monkeypatch):
    """The mesh is built after the frame loop: when it cannot be (here: a grid budget of 20
    blocks), the trajectory, timing.json and run.json are still written, run.json records
    the failure and the command ends with one line and status 2."""
    import functools

    from typer.testing import CliRunner

    import dynastereo.mesh.fusion as fusion
    from dynastereo.cli.main import app
    from dynastereo.mesh.tsdf import BLOCK_BYTES
    from dynastereo.synth import generate

    monkeypatch.setattr(fusion, "TSDFVolume", functools.partial(TSDFVolume, max_bytes=20 * BLOCK_BYTES))
    seq = generate(tmp_path / "seq", "oncoming", frames=8, seed=3, size=(480, 144))
    out = tmp_path / "run"
    r = CliRunner().invoke(app, ["run", str(seq), "--out", str(out), "--detector", "oracle", "--save-mesh",
                                 str(out / "world.ply")])
    assert r.exit_code == 2, r.output
    assert "voxel grid would need more than" in r.output and "Traceback" not in r.output
    run = json.loads((out / "run.json").read_text())
    assert run["status"].startswith("failed") and "mesh.voxel_size" in run["mesh"]["error"]
    assert len((out / "trajectory.kitti.txt").read_text().splitlines()) == run["frames_done"] == 8
    assert (out / "timing.json").is_file() and not (out / "world.ply").exists()


def test_run_writes_the_mesh_the_log_counts(tmp_path: Path):
    """A whole run (synthetic, oracle boxes) with --save-mesh / --save-dense-cloud: the PLY
    loads with plyfile, its vertex count is the one printed and in run.json; the report and
    the rerun recording show the mesh; a mask job refuses --save-mesh."""
    plyfile = pytest.importorskip("plyfile")
    from typer.testing import CliRunner

    from dynastereo.cli.main import app
    from dynastereo.synth import generate

    seq = generate(tmp_path / "seq", "oncoming", frames=14, seed=3, size=(480, 144))
    out = tmp_path / "run"
    runner = CliRunner()
    r = runner.invoke(app, ["run", str(seq), "--out", str(out), "--detector", "oracle", "--save-mesh",
                            str(out / "world.ply"), "--save-dense-cloud", str(out / "dense.ply"), "--report",
                            "--rrd", str(tmp_path / "run.rrd")])
    assert r.exit_code == 0, r.output
    info = json.loads((out / "run.json").read_text())["mesh"]
    ply = plyfile.PlyData.read(str(out / "world.ply"))
    n = ply["vertex"].count
    assert n == info["vertices"] > 1000 and ply["face"].count == info["triangles"]
    assert f"static world: {n} vertices" in " ".join(r.output.split())
    assert plyfile.PlyData.read(str(out / "dense.ply"))["vertex"].count == n
    assert info["keyframes"] >= 2 and info["masked"] is True
    page = (out / "report.html").read_text()
    assert "<h2>Static world</h2>" in page and 'data-key="mesh.vertices">' + str(n) in page
    # the rerun recording holds it
    from dynastereo.viz.rerun import recorded_entities

    assert "/world/static_mesh" in recorded_entities(tmp_path / "run.rrd")
    bad = runner.invoke(app, ["mask", str(seq), "--out", str(tmp_path / "m"), "--save-mesh", "x.ply"])
    assert bad.exit_code != 0


def _small_mesh() -> Mesh:
    vol = TSDFVolume(0.1, 0.3, 1)
    v, _ = np.mgrid[0:H, 0:W]
    depth = np.where(v > CY, F * HEIGHT / np.maximum(v - CY, 1e-6), 0).astype(np.float32)
    depth[depth > 8] = 0
    vol.integrate(depth, np.full((H, W), 90, np.uint8), CALIB.K, np.eye(4)[:3])
    return vol.mesh()


def test_mesh_marker_serializes_for_ros1_and_ros2():
    from dynastereo.ros.messages import RosbagsBuilder

    mesh = _small_mesh()
    assert len(mesh.faces) > 50
    for ros1 in (True, False):
        b = RosbagsBuilder(ros1)
        raw = b.serialize(b.mesh_marker(mesh, 5_000_000, "odom"))
        back = (b.typestore.deserialize_ros1 if ros1 else b.typestore.deserialize_cdr)(
            raw, "visualization_msgs/msg/Marker")
        assert back.type == 11 and len(back.points) == 3 * len(mesh.faces) == len(back.colors)
        f0 = mesh.vertices[mesh.faces[0]]
        assert [back.points[0].x, back.points[0].y, back.points[0].z] == pytest.approx(f0[0].tolist(), abs=1e-5)
        assert back.colors[0].r == pytest.approx(90 / 255, abs=0.01)


def test_live_core_builds_the_mesh_on_request(tmp_path: Path):
    """The live node's core keeps the keyframes when asked (``mesh``) and fuses them on
    request; without it there is nothing to build."""
    from dynastereo.io import KittiSequence
    from dynastereo.ros.core import StereoInput, StereoNodeCore
    from dynastereo.synth import generate

    seq = KittiSequence(generate(tmp_path / "seq", "static", frames=8, seed=1, size=(480, 144)))
    cfg = Config().with_overrides({"masker.kind": "none"})
    core = StereoNodeCore(cfg, calibration=seq.calibration, mesh=True)
    plain = StereoNodeCore(cfg, calibration=seq.calibration)
    try:
        for i in range(8):
            f = seq.frame(i)
            core.process(StereoInput(f.left, f.right, int(i * 100_000_000)))
        res = core.build_mesh()
        assert res is not None and res.stats.keyframes >= 1 and len(res.mesh.vertices) > 1000
        assert plain.build_mesh() is None
        # the build_mesh service both nodes serve: the file, the two messages, the counts
        from dynastereo.ros.messages import RosbagsBuilder

        class Pub:
            def __init__(self) -> None:
                self.sent: list = []

            def publish(self, msg) -> None:
                self.sent.append(msg)

        pm, pd = Pub(), Pub()
        ok, msg = core.mesh_service(RosbagsBuilder(False), tmp_path / "save", pm, pd)
        info = json.loads(msg)
        assert ok and Path(info["file"]) == tmp_path / "save" / "mesh.ply" and Path(info["file"]).is_file()
        assert info["vertices"] == len(res.mesh.vertices) and pm.sent[0].type == 11
        assert pd.sent[0].width * pd.sent[0].height == info["vertices"]
        last = core._stamps[-1]  # stamped with the last published pair
        assert (pm.sent[0].header.stamp.sec, pm.sent[0].header.stamp.nanosec) == divmod(last, 1_000_000_000)
        assert plain.mesh_service(RosbagsBuilder(False), tmp_path / "p", None, None) == (
            False, "started without mesh: true")
    finally:
        core.shutdown()
        plain.shutdown()


def test_report_shows_the_mesh_and_the_unmasked_one_beside(tmp_path: Path):
    from dynastereo.eval.html_report import build_report

    mesh = _small_mesh()
    write_mesh_ply(tmp_path / "world.ply", mesh)
    write_mesh_ply(tmp_path / "world_unmasked.ply", mesh)
    info = {"vertices": len(mesh.vertices), "triangles": len(mesh.faces), "keyframes": 1, "voxel_bytes": 1000,
            "file": str(tmp_path / "world.ply"), "unmasked_file": str(tmp_path / "world_unmasked.ply"),
            "camera": {"fx": F, "fy": F, "cx": CX, "cy": CY, "width": W, "height": H}}
    (tmp_path / "run.json").write_text(json.dumps({"status": "done", "frames_done": 1, "mesh": info}))
    page = build_report(tmp_path, auto_gt=False).read_text()
    assert "<h2>Static world</h2>" in page
    for label in ("movers left out", "the same fusion without masks"):
        assert f"from above, {label}" in page and f"from the first camera, {label}" in page
