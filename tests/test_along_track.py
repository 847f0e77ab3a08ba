"""The reported position smoothed along the map's path (service/estimators/along_track.py)."""

from __future__ import annotations

import numpy as np

from client.dataset import Round
from client.lab.experiments import SimilarityTable
from service.engine.localizer import Localizer
from service.estimators.along_track import AlongTrackSmoother, path_tangent
from service.maps.route_map import RouteMap


def test_path_tangent_follows_the_image_order_and_ignores_far_neighbours() -> None:
    line = np.column_stack([np.arange(5.0), np.zeros(5)])
    assert np.allclose(path_tangent(line, 2, 1.0), [1, 0])
    assert np.allclose(path_tangent(line, 0, 1.0), [1, 0])  # an end: one-sided
    assert np.allclose(path_tangent(line, 4, 1.0), [1, 0])
    # a second traversal starts far away: its first image is no neighbour of the last one
    two = np.vstack([line, line[::-1] + np.array([0.0, 50.0])])
    assert np.allclose(path_tangent(two, 4, 1.0), [1, 0])
    assert np.allclose(path_tangent(two, 5, 1.0), [-1, 0])
    assert path_tangent(np.array([[0.0, 0.0], [100.0, 0.0]]), 0, 1.0) is None


def _track(truth: np.ndarray, z: np.ndarray, tangents: list[np.ndarray | None],
           alpha: float) -> np.ndarray:
    s = AlongTrackSmoother()
    return np.array([s.update(zi, t, alpha, 10.0) for zi, t in zip(z, tangents,
                                                                          strict=True)])


def test_scatter_along_the_path_is_smoothed_and_an_offset_across_it_is_not() -> None:
    rng = np.random.default_rng(4)
    n = 200
    truth = np.column_stack([np.arange(n, dtype=float), np.full(n, 1.0)])  # 1 m beside
    z = truth + np.column_stack([rng.uniform(-1.5, 1.5, n), np.zeros(n)])
    out = _track(truth, z, [np.array([1.0, 0.0])] * n, 0.5)
    raw = np.abs(z[20:, 0] - truth[20:, 0]).mean()
    assert np.abs(out[20:, 0] - truth[20:, 0]).mean() < 0.75 * raw
    assert np.allclose(out[:, 1], 1.0)  # across the path the measurement counts in full
    off = _track(truth, z, [np.array([1.0, 0.0])] * n, 1.0)  # alpha 1: no smoothing
    assert np.allclose(off, z)


def test_a_turn_does_not_lag_as_a_two_dimensional_smoother_does() -> None:
    k = 30  # east for 30 frames at 1 m per frame, then north
    truth = np.vstack([np.column_stack([np.arange(k, dtype=float), np.zeros(k)]),
                       np.column_stack([np.full(k, k - 1.0), np.arange(1, k + 1.0)])])
    east, north = np.array([1.0, 0.0]), np.array([0.0, 1.0])
    tangents: list[np.ndarray | None] = [east] * k + [north] * k
    along = _track(truth, truth, tangents, 0.5)
    # the same filter damping both directions: the old velocity carries it past the corner
    s, flat = AlongTrackSmoother(), []
    for zi in truth:
        if s.position is None:
            flat.append(s.update(zi, None, 0.5, 10.0))
            continue
        pred = s.position + s.velocity
        s.position = pred + 0.5 * (zi - pred)
        s.velocity = s.velocity + 0.5**2 / 1.5 * (zi - pred)  # the same beta
        flat.append(s.position.copy())
    err_along = np.linalg.norm(along - truth, axis=1)[k:]
    err_flat = np.linalg.norm(np.array(flat) - truth, axis=1)[k:]
    assert err_along.max() < 0.8 * err_flat.max()
    assert err_along.mean() < 0.8 * err_flat.mean()


def test_a_jump_longer_than_the_gate_is_reported_at_once() -> None:
    s = AlongTrackSmoother()
    t = np.array([1.0, 0.0])
    for i in range(10):
        s.update(np.array([float(i), 0.0]), t, 0.5, 10.0)
    far = np.array([60.0, 20.0])
    assert np.allclose(s.update(far, t, 0.5, 10.0), far)
    assert np.allclose(s.velocity, 0.0)  # standing: no tracked velocity given
    back = np.array([61.0, 20.0])
    assert np.allclose(s.update(back + 30.0, t, 0.5, 10.0, velocity=np.array([1.0, 0.0])),
                       back + 30.0)
    assert np.allclose(s.velocity, [1.0, 0.0])  # a restart keeps the tracked velocity


def test_the_swarm_is_the_same_with_and_without_the_smoothing(
        small_map: RouteMap, table: SimilarityTable, sunny2: Round) -> None:
    """Smoothing changes what is reported, never what the swarm does."""
    n = len(sunny2)
    on = Localizer(small_map, "dpso", None, seed=5)
    off = Localizer(small_map, "dpso", {"along_track_alpha": 1.0}, seed=5)
    differ = 0
    for it in range(60):
        a, b = (loc.estimator.step(lambda ids, q=it % n: table.scores(q, ids), float(it))
                for loc in (on, off))
        assert np.array_equal(on.estimator.particles(), off.estimator.particles())
        assert a.status == b.status and np.array_equal(a.covariance, b.covariance)
        if a.status.value == "tracking":
            differ += not np.allclose(a.position, b.position)
        else:
            assert np.array_equal(a.position, b.position)
    assert differ > 20
