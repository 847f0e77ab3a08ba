"""Relative lost detection and the sub-swarm grouping of the multi-swarm DPSO."""

from __future__ import annotations

import numpy as np

from service.estimators.lost_detection import DistinctnessMonitor
from service.estimators.multi_swarm_dpso import speciate


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
