"""The map's tables (``MapPoints``, ``Observations``): growth, the vectorized point
updates, the per-point observation lists, and their own ``to_arrays`` / ``from_arrays``
(the map-file entries) with checks that name the entry."""

from __future__ import annotations

import numpy as np
import pytest

from dynastereo.errors import MapFileError
from dynastereo.slam.geometry import inv_T
from dynastereo.slam.map_points import MapPoints
from dynastereo.slam.observations import Observations


def _points(n: int = 10, capacity: int = 2) -> MapPoints:
    rng = np.random.default_rng(0)
    P = MapPoints(capacity)
    P.add(rng.normal(size=(n // 2, 3)), rng.integers(0, 256, (n // 2, 32), dtype=np.uint8), 0)
    P.add(rng.normal(size=(n - n // 2, 3)), rng.integers(0, 256, (n - n // 2, 32), dtype=np.uint8), 1)
    P.normal[:n] = np.array([0.0, 0.0, 1.0])
    return P


def test_points_grow_and_count_like_orbslam() -> None:
    P = _points(10)
    assert P.n == 10 and len(P.pos) >= 10
    np.testing.assert_array_equal(P.first_kf[:10], [0] * 5 + [1] * 5)
    assert (P.visible[:10] == 1).all() and (P.found[:10] == 1).all() and (P.replaced[:10] == -1).all()
    # a repeated id counts once (ORB-SLAM2 increases each point once per frame)
    P.mark_visible(np.array([2, 2, 3]))
    P.mark_found(np.array([2]))
    assert (P.visible[2], P.visible[3], P.found[2]) == (2, 2, 2)
    np.testing.assert_allclose(P.found_ratio(np.array([2, 3])), [1.0, 0.5])
    P.bad[4] = True
    P.replaced[4] = 7
    P.replaced[7] = 8
    np.testing.assert_array_equal(P.good(np.array([-1, 3, 4])), [False, True, False])
    np.testing.assert_array_equal(P.resolve(np.array([-1, 3, 4])), [-1, 3, 8])
    assert 4 not in P.good_ids() and len(P.good_ids()) == 9


def test_transform_moves_positions_and_normals() -> None:
    P = _points(6)
    X0, N0 = P.pos[:6].copy(), P.normal[:6].copy()
    c, s = np.cos(0.3), np.sin(0.3)
    T = np.array([[c, -s, 0, 1.0], [s, c, 0, 2.0], [0, 0, 1, 3.0], [0, 0, 0, 1]])
    P.transform(np.arange(3), T)
    np.testing.assert_allclose(P.pos[:3], X0[:3] @ T[:3, :3].T + T[:3, 3])
    np.testing.assert_allclose(P.normal[:3], N0[:3] @ T[:3, :3].T)
    np.testing.assert_array_equal(P.pos[3:6], X0[3:6])
    # one transform per point; the inverse brings them back
    Ts = np.stack([inv_T(T)] * 3)
    P.transform(np.arange(3), Ts)
    np.testing.assert_allclose(P.pos[:3], X0[:3], atol=1e-12)
    np.testing.assert_allclose(P.normal[:3], N0[:3], atol=1e-12)


def test_observation_lists_and_erase() -> None:
    obs = Observations(1, 1)
    obs.add_points(4)
    r0 = obs.add(0, np.array([10, 11, 12]), np.array([0, 1, 2]))
    r1 = obs.add(1, np.array([20, 21]), np.array([1, 3]))
    np.testing.assert_array_equal(r0, [0, 1, 2])
    np.testing.assert_array_equal(r1, [3, 4])
    np.testing.assert_array_equal(obs.rows_of(np.array([1, 1, -1])), [1, 3])
    p, kfs = obs.first_observers(np.array([1, 3]))
    np.testing.assert_array_equal(p, [1, 3])
    np.testing.assert_array_equal(kfs, [0, 1])
    obs.erase(np.array([1]))
    np.testing.assert_array_equal(obs.rows_of(np.array([1])), [3])
    assert obs.n_alive() == 4 and obs.n == 5


def test_tables_round_trip_through_their_arrays() -> None:
    P = _points(7)
    P.bad[3] = True
    back = MapPoints.from_arrays(P.to_arrays())
    assert back.n == 7 and list(back.to_arrays()) == list(MapPoints.entries())
    for k, a in P.to_arrays().items():
        b = back.to_arrays()[k]
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), k
    obs = Observations()
    obs.add_points(7)
    obs.add(0, np.array([1, 2]), np.array([3, 5]))
    arrays = obs.to_arrays()
    assert list(arrays)[0] == "points/head" and len(arrays["points/head"]) == 7
    ob = Observations.from_arrays(arrays)
    np.testing.assert_array_equal(ob.rows_of(np.array([5])), [1])
    # and it grows again beyond the loaded (trimmed) arrays
    ob.add_points(8)
    ob.add(1, np.array([0]), np.array([7]))
    np.testing.assert_array_equal(ob.rows_of(np.array([7])), [2])


@pytest.mark.parametrize(
    "change, pattern",
    [
        (lambda a: a.pop("points/found"), "entry 'points/found' is missing"),
        (lambda a: a.update({"points/pos": a["points/pos"].astype(np.float32)}),
         "entry 'points/pos' has dtype float32, expected float64"),
        (lambda a: a.update({"points/desc": a["points/desc"][:, :16]}), r"entry 'points/desc' has shape \(5, 16\)"),
        (lambda a: a.update({"points/bad": a["points/bad"][:4]}), r"entry 'points/bad' has shape \(4,\)"),
    ],
)
def test_from_arrays_names_the_bad_entry(change, pattern) -> None:
    arrays = dict(_points(5).to_arrays())
    change(arrays)
    with pytest.raises(MapFileError, match=pattern):
        MapPoints.from_arrays(arrays)
