"""A far jump of the reported place is not ``tracking`` until confirmed (report only)."""

from __future__ import annotations

import numpy as np

from service.api.params import DPSOParams
from service.estimators.base import Status
from service.estimators.jump_hold import JumpHold
from service.estimators.multi_swarm_dpso import MultiSwarmDPSO
from tests.line_index import LineIndex

STEP = np.array([0.6, 0.0])


def _walk(hold: JumpHold, start: float, n: int, good: bool = True, located: bool = False,
          limit_m: float = 10.0) -> list[float]:
    """``n`` frames 0.6 m apart from ``start`` (x, m), the tracked step predicting each."""
    return [hold.judge(np.array([start + 0.6 * k, 0.0]), STEP, limit_m, good, located, 5)
            for k in range(n)]


def test_moving_with_the_predicted_step_is_never_held() -> None:
    hold = JumpHold()
    assert _walk(hold, 0.0, 30) == [0.0] * 30
    # a correction of a few metres is no jump; the first frame has nothing to jump from
    assert hold.judge(np.array([0.6 * 30 + 4.0, 0.0]), STEP, 10.0, False, False, 5) == 0.0


def test_a_far_jump_is_held_until_five_good_frames_in_a_row() -> None:
    hold = JumpHold()
    _walk(hold, 0.0, 10)  # at 5.4 m, predicting 6.0
    held = _walk(hold, 60.0, 4, good=True)  # a look-alike 54 m ahead: good frames there
    assert held[0] > 50 and held == [held[0]] * 4
    assert hold.judge(np.array([62.4, 0.0]), STEP, 10.0, False, False, 5) == held[0]  # bad
    # the bad frame restarted the count: five more good ones end the hold
    rest = [hold.judge(np.array([63.0 + 0.6 * k, 0.0]), STEP, 10.0, True, False, 5)
            for k in range(5)]
    assert rest[:4] == [held[0]] * 4 and rest[4] == 0.0


def test_a_located_good_frame_confirms_the_new_place_at_once() -> None:
    hold = JumpHold()
    _walk(hold, 0.0, 10)
    assert _walk(hold, 60.0, 2, good=False)[0] > 50  # not confirmed: still held
    assert hold.judge(np.array([61.2, 0.0]), STEP, 10.0, False, True, 5) > 50  # located, bad
    assert hold.judge(np.array([61.8, 0.0]), STEP, 10.0, True, True, 5) == 0.0


def test_the_hold_is_off_at_zero() -> None:
    hold = JumpHold()
    _walk(hold, 0.0, 10, limit_m=0.0)
    assert _walk(hold, 60.0, 5, good=False, limit_m=0.0) == [0.0] * 5


def test_a_swarm_that_moves_to_a_far_place_earns_tracking_there_later_positions_unchanged(
        ) -> None:
    """A robot tracked along a 120 m line of images; from frame 40 its images stop matching
    and a place 48 m ahead matches instead (a look-alike, or a kidnap). The swarm finds it,
    the same way with and without the hold (the same positions, bit for bit); with the hold
    the new place is reported ``recovering`` for longer, with an ``accuracy_m`` at least the
    jump, before it is ``tracking``."""
    line = LineIndex(200, 0.6)

    def m(ids: np.ndarray, at: int) -> np.ndarray:
        return 0.3 * np.exp(-np.abs(np.asarray(ids) - at)) + 0.01

    def replay(params: DPSOParams) -> list[tuple[np.ndarray, Status, float]]:
        est = MultiSwarmDPSO(line, params, np.random.default_rng(3))
        out = []
        for k in range(90):
            at = 20 + k if k < 40 else 100 + k  # from frame 40 the place 48 m ahead
            r = est.step(lambda ids, at=at: m(ids, at), float(k))
            out.append((r.position, r.status, r.accuracy_m))
        return out

    held, free = replay(DPSOParams()), replay(DPSOParams(jump_hold_m=0))
    assert all(np.array_equal(a[0], b[0]) for a, b in zip(held, free, strict=True))
    assert held[39][1] is Status.TRACKING
    jumped = next(k for k in range(40, 90) if held[k][0][0] - held[k - 1][0][0] > 10)
    first_free = next(k for k in range(jumped, 90) if free[k][1] is Status.TRACKING)
    first_held = next(k for k in range(jumped, 90) if held[k][1] is Status.TRACKING)
    assert first_held > first_free  # three good frames end DPSO's recovery, five the hold
    assert all(held[k][1] is Status.RECOVERING and held[k][2] > 10
               for k in range(first_free, first_held))
    assert held[-1][1] is Status.TRACKING and abs(held[-1][0][0] - 0.6 * 189) < 2


def test_a_jump_to_another_place_does_not_teach_the_velocity() -> None:
    """The swarm's estimate jumps 48 m ahead to the place that now matches (a look-alike, a
    kidnap, or the search's first find): that displacement is not motion. The velocity the
    frames before it taught holds through the jump (0.6 m per frame along the line); with the
    gate set beyond the jump, the jump teaches it (the contrast): the speed after it is more
    than twice the robot's. (The search's wild estimates before it are weak frames, which
    teach nothing either way.)"""
    line = LineIndex(200, 0.6)

    def m(ids: np.ndarray, at: int) -> np.ndarray:
        return 0.3 * np.exp(-np.abs(np.asarray(ids) - at)) + 0.01

    def speeds(params: DPSOParams) -> list[float]:
        est = MultiSwarmDPSO(line, params, np.random.default_rng(3))
        out = []
        for k in range(60):
            at = 20 + k if k < 40 else 100 + k
            est.step(lambda ids, at=at: m(ids, at), float(k))
            out.append(est.motion(1.0)[0])
        return out

    gated, taught = speeds(DPSOParams()), speeds(DPSOParams(along_track_gate_m=1e4))
    assert all(abs(s - 0.6) < 0.1 for s in gated[35:])
    assert max(taught[40:]) > 1.2
