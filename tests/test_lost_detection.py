"""Relative lost detection and the sub-swarm grouping of the multi-swarm DPSO."""

from __future__ import annotations

import numpy as np

from service.engine.localizer import Localizer
from service.estimators.lost_detection import DistinctnessMonitor, vouch
from service.estimators.multi_swarm_dpso import speciate
from service.maps.route_map import RouteMap


def _monitor() -> DistinctnessMonitor:
    return DistinctnessMonitor(min_ratio=3.0, floor_m=0.004, far_m=10.0, alpha=0.5)


def test_weak_but_distinct_match_is_good_and_flat_one_is_not() -> None:
    pos = np.array([[0.0, 0.0], [1.0, 0.0], [30.0, 0.0], [60.0, 0.0], [90.0, 0.0]])
    mon = _monitor()
    # changed light: the true place matches only 2 %, yet stands out of a 0.4 % background
    ev = mon.judge(pos, np.array([0.02, 0.015, 0.004, 0.005, 0.003]), pos[0], 5.0)
    assert ev.good and ev.distinct >= 5
    # elsewhere: nothing stands out, whatever the level
    mon = _monitor()
    ev = mon.judge(pos, np.array([0.05, 0.04, 0.045, 0.05, 0.04]), pos[0], 5.0)
    assert not ev.good and ev.distinct < 2
    # no structure at all (night): never good, even if a ratio of tiny numbers is large
    mon = _monitor()
    assert not mon.judge(pos, np.array([0.003, 0.0, 0.0, 0.0, 0.0]), pos[0], 5.0).good


def test_background_is_remembered_when_no_far_image_was_compared() -> None:
    mon = _monitor()
    far = np.array([[0.0, 0.0], [40.0, 0.0], [80.0, 0.0]])
    mon.judge(far, np.array([0.1, 0.01, 0.01]), far[0], 5.0)
    near_only = np.array([[0.0, 0.0], [1.0, 0.0]])
    ev = mon.judge(near_only, np.array([0.012, 0.011]), near_only[0], 5.0)
    assert ev.background == 0.01 and not ev.good  # 1.2x the remembered background
    mon.reset()
    assert mon.background is None


def test_a_scout_finding_the_place_does_not_vouch_for_a_wrong_estimate() -> None:
    pos = np.array([[0.0, 0.0], [1.0, 0.0], [60.0, 0.0], [90.0, 0.0], [120.0, 0.0]])
    scores = np.array([0.006, 0.005, 0.2, 0.005, 0.004])  # the true place is at x = 60
    assert not _monitor().judge(pos, scores, pos[0], 5.0).good  # the estimate is at 0
    assert _monitor().judge(pos, scores, pos[2], 5.0).good


def test_speciate_groups_particles_around_the_best_seeds() -> None:
    x = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [50.0, 0.0], [51.0, 0.0], [200.0, 0.0]])
    f = np.array([0.5, 0.9, 0.1, 0.3, 0.2, 0.05])
    seeds, label = speciate(x, f, radius=5.0, max_species=2)
    assert seeds.tolist() == [1, 3]
    assert label.tolist() == [0, 0, 0, 1, 1, -1]  # the third group exceeds max_species


def test_the_first_type_vouches_only_where_the_fused_m_stands_out_somewhat() -> None:
    pos = np.array([[0.0, 0.0], [1.0, 0.0], [30.0, 0.0], [60.0, 0.0], [90.0, 0.0]])
    # the fused m at the estimate 2.5x its background: in doubt (distinct_ratio 3)
    fused = _monitor().judge(pos, np.array([0.025, 0.02, 0.01, 0.01, 0.01]), pos[0], 5.0)
    own = _monitor().judge(pos, np.array([0.05, 0.03, 0.005, 0.004, 0.005]), pos[0], 5.0)
    assert not fused.good and 2.0 <= fused.distinct < 3.0 and own.good
    ev = vouch(fused, own, 2.0)
    assert ev.good and ev.vouched and ev.distinct == own.distinct and ev.best_m == fused.best_m
    assert vouch(fused, own, 3.0) is fused  # it stands out less than asked
    assert vouch(fused, own, 0.0) is fused  # vouching off
    flat = _monitor().judge(pos, np.array([0.006, 0.005, 0.005, 0.005, 0.005]), pos[0], 5.0)
    assert vouch(fused, flat, 2.0) is fused  # the first type sees nothing either
    good = _monitor().judge(pos, np.array([0.05, 0.04, 0.01, 0.01, 0.01]), pos[0], 5.0)
    assert vouch(good, own, 2.0) is good and not good.vouched  # nothing to vouch for


def test_a_vouched_frame_holds_tracking_but_never_restores_it(small_map: RouteMap) -> None:
    """Frames whose fused m is in doubt (2.5x its background) and whose first type's m is
    clear: with vouching a tracking session stays tracking; without, it is lost; once lost
    (frames that match nothing), the same frames do not bring it back, and clear frames do."""
    place = small_map.positions[len(small_map.positions) // 2]
    near = np.linalg.norm(small_map.positions - place, axis=1) <= 2.0

    def m_of(at_place: float, elsewhere: float):
        return lambda ids: np.where(near[ids], at_place, elsewhere)

    clear, doubtful, nothing = m_of(0.2, 0.01), m_of(0.025, 0.01), m_of(0.01, 0.01)
    own_clear = m_of(0.05, 0.004)

    def status_after(vouch_distinct: float, plan: list[tuple[int, object]]) -> list[str]:
        loc = Localizer(small_map, "dpso", {"vouch_distinct": vouch_distinct}, seed=3)
        est = loc.estimator
        out, t = [], 0.0
        for n, sim in plan:
            for _ in range(n):
                out.append(est.step(sim, t, first=own_clear).status.value)  # type: ignore[arg-type]
                t += 1.0
        return out

    settle = (30, clear)
    held = status_after(2.0, [settle, (20, doubtful)])
    assert held[29] == "tracking" and set(held[30:]) == {"tracking"}
    dropped = status_after(0.0, [settle, (20, doubtful)])
    assert dropped[29] == "tracking" and "tracking" not in dropped[-10:]
    lost_then = status_after(2.0, [settle, (10, nothing), (20, doubtful), (20, clear)])
    assert lost_then[29] == "tracking" and lost_then[39] != "tracking"
    assert "tracking" not in lost_then[40:60]  # vouched frames never restore it
    assert lost_then[-1] == "tracking"
