"""The multi-swarm DPSO's estimate: the images' place, and coasting through weak frames."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from client.dataset import Round
from client.lab.experiments import SimilarityTable
from service.api.params import DPSOParams
from service.engine.localizer import Localizer
from service.estimators.multi_swarm_dpso import image_centre, match_sigma
from service.maps.route_map import RouteMap


def test_image_centre_weights_images_by_their_match() -> None:
    xy = np.array([[0.0, 0.0], [2.0, 0.0], [30.0, 0.0]])
    m = np.array([0.02, 0.01, 0.5])  # the far image is outside the radius
    c = image_centre(xy, m, np.array([0.5, 0.0]), 4.0, 8.0)
    assert c[0] == pytest.approx(2.0 / (2**8 + 1), abs=1e-9) and c[1] == 0.0
    flat = image_centre(xy, m, np.array([0.5, 0.0]), 4.0, 0.0)  # power 0: plain centre
    assert flat[0] == pytest.approx(1.0)
    nothing = image_centre(xy, np.zeros(3), np.array([7.0, 1.0]), 4.0, 8.0)
    assert nothing.tolist() == [7.0, 1.0]


def test_match_sigma_grows_as_the_best_match_weakens() -> None:
    p = DPSOParams()
    sig = [match_sigma(m, p) for m in (0.5, 0.1, 0.02, 0.005)]
    assert all(a < b for a, b in itertools.pairwise(sig))
    assert match_sigma(0.1, p) == pytest.approx(p.match_sigma_m * 0.1 ** -p.match_sigma_power)
    # no match at all: the floor's sigma, finite
    assert match_sigma(0.0, p) == match_sigma(p.distinct_floor_m, p) < 10
    assert match_sigma(0.02, p.with_overrides({"match_sigma_m": 0.0})) == 0.0


def _run_with_blackout(small_map: RouteMap, table: SimilarityTable, n: int,
                       params: dict[str, float] | None, start: int, blackout: range
                       ) -> tuple[np.ndarray, np.ndarray]:
    """(estimates, speeds) of a run whose frames in ``blackout`` match every map image
    equally weakly (as under a change of light where nothing stands out)."""
    loc = Localizer(small_map, "dpso", params, seed=start)
    out, speed = [], []
    for it in range(blackout.stop + 15):
        q = (start + it) % n
        if it in blackout:
            res = loc.estimator.step(lambda ids: np.full(len(ids), 0.003), float(it))
        else:
            res = loc.estimator.step(lambda ids, q=q: table.scores(q, ids), float(it))
        out.append(res.position)
        speed.append(res.speed_mps)
    return np.array(out), np.array(speed)


def test_weak_frames_keep_the_tracked_velocity_and_tracking_resumes(
        small_map: RouteMap, table: SimilarityTable, sunny2: Round) -> None:
    truth = sunny2.reference_xy
    n = len(sunny2)
    blackout = range(40, 50)
    a, b = blackout.start - 1, blackout.stop - 1
    for start in (0, n // 3, 2 * n // 3):
        frames = (start + np.arange(blackout.stop + 15)) % n
        est, speed = _run_with_blackout(small_map, table, n, None, start, blackout)
        assert np.linalg.norm(est[a] - truth[frames[a]]) < 3  # tracking before
        # through the weak frames the speed is the one tracked before them, not learnt from
        # estimates that lag where every place looks alike
        assert np.allclose(speed[a:b + 1], speed[a]) and speed[a] > 0.1
        # after them the images take over again
        assert np.linalg.norm(est[-1] - truth[frames[-1]]) < 3
        # without coasting the weak estimates feed the speed
        _, stall = _run_with_blackout(small_map, table, n, {"coast_ratio": 0.0}, start,
                                      blackout)
        assert not np.allclose(stall[a:b + 1], stall[a])


def test_a_lasting_drop_of_the_match_level_becomes_the_new_level(small_map: RouteMap) -> None:
    loc = Localizer(small_map, "dpso", {"coast_max_frames": 5}, seed=0)
    est = loc.estimator
    judge = est._judge_weak  # type: ignore[attr-defined]
    for _ in range(10):  # tracking at a level of 0.04
        assert not judge(0.04, True)
    weak = [judge(0.01, True) for _ in range(12)]  # the level drops to a quarter for good
    assert weak[:5] == [True] * 5  # coasted through as a weak stretch at first ...
    assert not any(weak[5:])  # ... then 0.01 is the new normal
    assert est.level == pytest.approx(0.01)  # type: ignore[attr-defined]
    assert judge(0.005, True)  # and a drop below 0.65 of it is weak again


def _annulus_comparisons(small_map: RouteMap, table: SimilarityTable, n: int,
                         params: dict[str, float] | None) -> list[int]:
    """Per frame after convergence: map images compared 4-15 m from the previous estimate."""
    loc = Localizer(small_map, "dpso", params, seed=1)
    xy = np.asarray(small_map.positions)
    counts, prev = [], None
    for it in range(40):
        asked: list[np.ndarray] = []

        def sim(ids: np.ndarray, q: int = it % n,
                asked: list[np.ndarray] = asked) -> np.ndarray:
            asked.append(np.asarray(ids))
            return table.scores(q, ids)

        res = loc.estimator.step(sim, float(it))
        if prev is not None and it >= 20:
            d = np.linalg.norm(xy[np.unique(np.concatenate(asked))] - prev, axis=1)
            counts.append(int(((d >= 4) & (d <= 15)).sum()))
        prev = res.position
    return counts


def test_local_scouts_search_around_the_estimate_every_other_frame(
        small_map: RouteMap, table: SimilarityTable, sunny2: Round) -> None:
    n = len(sunny2)
    counts = _annulus_comparisons(small_map, table, n, None)
    # every other frame, round(0.1 * 80) = 8 scouts land 4-15 m from the estimate (some may
    # share an image, and the global scouts land anywhere)
    assert max(counts[0::2]) >= 5 or max(counts[1::2]) >= 5
    busy = counts[0::2] if max(counts[0::2]) >= 5 else counts[1::2]
    assert min(busy) >= 4
    # without them the swarm compares next to nothing there
    quiet = _annulus_comparisons(small_map, table, n, {"local_scout_ratio": 0.0})
    assert np.mean(quiet) < 0.5 * np.mean(busy)


def test_map_positions_near_lie_in_the_annulus(small_map: RouteMap) -> None:
    est = Localizer(small_map, "dpso", {"init_spread_m": 0.0}, seed=0).estimator
    xy = np.asarray(small_map.positions)
    centre = xy[len(xy) // 2]
    pts = est.sample_map_positions_near(centre, 4.0, 15.0, 200)
    d = np.linalg.norm(pts - centre, axis=1)
    assert (d >= 4.0).all() and (d <= 15.0).all()
    assert len(np.unique(pts, axis=0)) > 5  # drawn among many images, not one
    # nothing in the annulus: the nearest image instead
    far = est.sample_map_positions_near(np.array([1e4, 1e4]), 0.0, 1.0, 3)
    nearest = xy[np.argmin(np.linalg.norm(xy - np.array([1e4, 1e4]), axis=1))]
    assert np.allclose(far, nearest)


def test_accuracy_widens_when_the_same_frame_matches_weaker(
        small_map: RouteMap, table: SimilarityTable, sunny2: Round) -> None:
    """The same swarm and frame, once with its similarities and once with a fifth of them
    (same ranking, as under other light): the same estimate, reported less sharply."""
    n = len(sunny2)
    twins = [Localizer(small_map, "dpso", None, seed=3) for _ in range(2)]
    for it in range(30):  # the same seed and frames: the same state
        res = [loc.estimator.step(lambda ids, q=it: table.scores(q, ids), float(it))
               for loc in twins]
    assert res[0].status.value == "tracking" and np.array_equal(res[0].position, res[1].position)
    q = 30 % n
    strong = twins[0].estimator.step(lambda ids: table.scores(q, ids), 30.0)
    weak = twins[1].estimator.step(lambda ids: 0.2 * table.scores(q, ids), 30.0)
    assert np.allclose(strong.position, weak.position)
    assert weak.accuracy_m > strong.accuracy_m * 1.1
