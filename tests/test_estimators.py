"""Estimators on rendered routes with the papers' defaults (no per-route tuning)."""

from __future__ import annotations

import numpy as np
import pytest

from client.lab.experiments import run
from client.runs import frames_to_recover
from service.api.params import ParamError
from service.engine.localizer import Localizer
from service.estimators.fitness import FrameFitness
from service.estimators.particle_filter import low_variance_resample
from service.estimators.registry import params_for
from tests.line_index import LineIndex

WARMUP = 20  # frames of global convergence left out of tracking errors


@pytest.fixture(scope="module")
def starts(sunny2) -> list[int]:
    return list(range(0, len(sunny2), len(sunny2) // 5))[:5]


def _mean_error(small_map, table, rnd, est, params, starts) -> tuple[float, float]:
    errs, comps = [], []
    for s in starts:
        res = run(small_map, table, rnd, est, params, seed=s, start=s)
        errs.append(res.errors[WARMUP:].mean())
        comps.append(res.comparisons[WARMUP:].mean())
    return float(np.mean(errs)), float(np.mean(comps))


def test_dpso_converges_globally_and_tracks(small_map, table, sunny2, starts) -> None:
    for s in starts[:3]:
        res = run(small_map, table, sunny2, "dpso", None, seed=s, start=s)
        assert res.errors[WARMUP:].mean() < 2.0
        assert np.mean(res.errors[WARMUP:] < 5.0) > 0.95
        assert res.status[0] == "initializing" and "tracking" in res.status


def test_dpso_accuracy_and_comparisons_vs_particle_filters(small_map, table, sunny2,
                                                           starts) -> None:
    dpso_err, dpso_cmp = _mean_error(small_map, table, sunny2, "dpso", None, starts)
    pfl_err, pfl_cmp = _mean_error(small_map, table, sunny2, "pf-l", {"n_particles": 300},
                                   starts)
    _, pfg_cmp = _mean_error(small_map, table, sunny2, "pf-g", {"n_particles": 300}, starts)
    assert dpso_err <= 1.1 * pfl_err
    assert dpso_cmp < pfl_cmp and dpso_cmp < pfg_cmp


def test_kidnapped_dpso_recovers(small_map, table, sunny2, starts) -> None:
    n = len(sunny2)
    frames: list[int | None] = []
    admitted: list[bool] = []
    for s in starts:
        res = run(small_map, table, sunny2, "dpso", None, seed=s, start=s, kidnap=True,
                  length=2 * n)
        frames.append(frames_to_recover(res))
        wrong = res.errors[n:] > 10  # the swarm still believes the old place
        admitted.extend(np.isin(np.array(res.status[n:])[wrong], ["recovering", "lost"]))
    assert all(f is not None for f in frames)
    assert np.median(frames) <= 30
    # while it is wrong, it says so (the relative lost detection) for a good share of the
    # frames: 56 % with dissolution by the evidence sum alone, 44 % since a young sub-swarm
    # that is better per frame survives (it often takes the estimate back to the true
    # place before the lost detection fires: 27 wrong frames instead of 32 over 5 runs);
    # 37 % (11 of 30) with OpenCV 5.0's SIFT on the same rendered world
    assert len(admitted) == 0 or np.mean(admitted) >= 1 / 3


def test_speed_estimate_of_tracking_swarm(small_map, table, sunny2, starts) -> None:
    for s in starts[:3]:
        res = run(small_map, table, sunny2, "dpso", None, seed=s, start=s)
        tracking = np.array(res.status) == "tracking"
        tracking[:40] = False  # the EMA needs a few frames after convergence
        ratio = np.median(res.speed[tracking]) / np.median(res.true_speed)
        assert abs(ratio - 1) < 0.2


@pytest.mark.parametrize(("estimator", "params"), [
    ("dpso", None), ("dpso", {"variant": "paper"}), ("pf-g", None), ("pf-l", None)])
def test_same_seed_same_estimates_bit_for_bit(small_map, table, sunny2, estimator,
                                              params) -> None:
    a = run(small_map, table, sunny2, estimator, params, seed=5, start=10, length=40)
    b = run(small_map, table, sunny2, estimator, params, seed=5, start=10, length=40)
    c = run(small_map, table, sunny2, estimator, params, seed=6, start=10, length=40)
    assert np.array_equal(a.est_xy, b.est_xy)
    assert np.array_equal(a.speed, b.speed)
    assert not np.array_equal(a.est_xy, c.est_xy)


def test_reset_near_a_known_pose(small_map, table, sunny2) -> None:
    loc = Localizer(small_map, "dpso", None, seed=1)
    truth = sunny2.truth_xy
    loc.reset(near=tuple(truth[50]), radius=3.0)
    e = loc.estimator.step(lambda ids: table.scores(50, ids), 0.0)
    assert np.linalg.norm(e.position - truth[50]) < 4.0
    assert e.comparisons < 20  # a local start compares only nearby images


def test_fitness_shares_comparisons_between_particles(small_map) -> None:
    calls: list[np.ndarray] = []

    def sim(ids: np.ndarray) -> np.ndarray:
        calls.append(ids.copy())
        return np.full(len(ids), 0.5)

    fit = FrameFitness(small_map, sim, penalty_sigma_m=2.0)
    pos = np.repeat(small_map.positions[[3, 7]], 10, axis=0)
    f, m, _ = fit(pos)
    assert fit.comparisons == 2 and len(calls) == 1
    np.testing.assert_allclose(f, 0.5)  # at an image position the penalty is 1
    np.testing.assert_allclose(m, 0.5)
    off = small_map.positions[[3]] + np.array([[0.0, 2.0]])  # about sigma off the route
    far = small_map.positions[[3]] + np.array([[0.0, 50.0]])
    f2, _, _ = fit(np.vstack([pos, off, far]))
    _, d_off = small_map.nearest(off)
    assert f2[-2] == pytest.approx(0.5 * np.exp(-0.5 * (d_off[0] / 2.0) ** 2))
    assert f2[-1] < 1e-6  # tens of metres from every map image
    assert len(calls) <= 2 and fit.comparisons <= 4  # ids already compared are not redone


def test_low_variance_resampling_keeps_proportions() -> None:
    rng = np.random.default_rng(0)
    w = np.array([0.5, 0.25, 0.25, 0.0])
    idx = low_variance_resample(rng, w)
    assert np.bincount(idx, minlength=4).tolist() == [2, 1, 1, 0]


def test_parameter_overrides_are_validated() -> None:
    assert params_for("dpso", {"n_particles": 40}).n_particles == 40
    with pytest.raises(ParamError, match="unknown parameter"):
        params_for("dpso", {"swarm": 3})
    with pytest.raises(ParamError, match="n_particles"):
        params_for("pf-l", {"n_particles": 0})
    with pytest.raises(ParamError, match="unknown estimator"):
        params_for("kalman")


def test_variants_are_selectable(small_map) -> None:
    from service.estimators.multi_swarm_dpso import MultiSwarmDPSO
    from service.estimators.paper_dpso import DPSO

    assert type(Localizer(small_map, "dpso").estimator) is MultiSwarmDPSO
    assert type(Localizer(small_map, "dpso", {"variant": "paper"}).estimator) is DPSO
    with pytest.raises(ParamError, match="variant"):
        params_for("dpso", {"variant": "papers"})


def test_estimate_reports_competing_hypotheses(small_map, table, sunny2) -> None:
    loc = Localizer(small_map, "dpso", None, seed=2)
    seen = []
    for it in range(12):
        res = loc.estimator.step(lambda ids, q=it: table.scores(q, ids), float(it))
        seen.append(res.hypotheses)
    # at a global start several places compete; the estimate follows the best-supported one
    assert max(len(h) for h in seen) >= 2
    for hyps in seen:
        if hyps:
            assert abs(sum(h.weight for h in hyps) - 1) < 1e-9
            assert hyps[0].weight == max(h.weight for h in hyps)


@pytest.mark.parametrize("by_mean", [True, False])  # dissolve_mean_ratio 1 and 0
def test_a_young_better_sub_swarm_survives_but_does_not_take_the_estimate(
        small_map, table, sunny2, by_mean) -> None:
    """A scout that lands on a place matching 1.6x better than the tracked one has one frame
    of evidence against the incumbent's five: judged by its mean evidence it survives (it is
    better, only younger); judged by the sum alone (``dissolve_mean_ratio`` 0) it is
    dissolved into the incumbent. Either way one frame does not move the estimate there."""
    loc = Localizer(small_map, "dpso", {"dissolve_mean_ratio": float(by_mean)}, seed=4)
    est = loc.estimator
    for it in range(30):
        res = est.step(lambda ids, q=it: table.scores(q, ids), float(it))
    assert res.status.value == "tracking"
    pos = np.asarray(small_map.positions)
    far = int(np.argmax(np.linalg.norm(pos - res.position, axis=1)))  # a place > 20 m away
    assert np.linalg.norm(pos[far] - res.position) > 20
    quantum = round(est.q_r * len(est.x))  # the first particles are redrawn every frame
    scout = quantum + int(np.argmin(est.evidence[quantum:]))
    est.x[scout] = pos[far]
    est.v[scout] = 0.0
    est.evidence[scout] = est.age[scout] = 0.0

    def boosted(ids: np.ndarray) -> np.ndarray:
        m = table.scores(30, ids)
        return np.where(ids == far, 1.6 * table.scores(30, np.arange(len(pos))).max(), m)

    after = est.step(boosted, 30.0)
    assert np.linalg.norm(after.position - res.position) < 5  # the estimate stayed
    # the scout itself (a random scout redrawn this frame may land anywhere, also there)
    assert (np.linalg.norm(est.x[scout] - pos[far]) < 3) == by_mean


def test_the_swarm_starts_fast_enough_for_a_map_with_images_far_apart() -> None:
    """v0 starts at two image spacings per frame where the papers' fraction of the map's
    extent is slower (ten images 2.5 m apart: capped at v0_max) and keeps the papers' value
    on a long map with images close together; a robot driven an image per frame there and
    back along the short map is tracked within one image on more frames."""
    from service.api.params import DPSOParams
    from service.estimators.base import Status
    from service.estimators.multi_swarm_dpso import MultiSwarmDPSO

    short, long_ = LineIndex(10, 2.5), LineIndex(200, 0.6)
    rng = np.random.default_rng
    assert MultiSwarmDPSO(short, DPSOParams(), rng(0)).v0 == DPSOParams().v0_max
    assert MultiSwarmDPSO(short, DPSOParams(v0_spacings=0), rng(0)).v0 == DPSOParams().v0
    assert MultiSwarmDPSO(long_, DPSOParams(), rng(0)).v0 == DPSOParams().v0

    def weak(ids: np.ndarray, i: int, k: int) -> np.ndarray:
        """A night frame's m: a low peak at the robot's image over noise that differs per
        frame and image (seeded by both)."""
        noise = [np.random.default_rng(1000 * k + int(j)).uniform() for j in np.ravel(ids)]
        return 0.02 * np.exp(-2 * np.abs(ids - i)) + 0.004 * np.reshape(noise, np.shape(ids)) \
            + 0.002

    def tracked_near(params: DPSOParams) -> int:
        order = np.tile(np.r_[np.arange(10), np.arange(8, 0, -1)], 4)
        hits = 0
        for seed in range(8):
            est = MultiSwarmDPSO(short, params, rng(seed))
            for k, i in enumerate(order):
                r = est.step(lambda ids, i=int(i), k=k: weak(ids, i, k), float(k))
                at = int(short.nearest(r.position[None])[0][0])
                hits += int(r.status is Status.TRACKING and abs(at - int(i)) <= 1)
        return hits

    # 8 runs x 72 frames: 532 against 443 when written
    assert tracked_near(DPSOParams()) > 1.1 * tracked_near(DPSOParams(v0_spacings=0))
