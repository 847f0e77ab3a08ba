"""The odometry's heading drift, estimated from located yaws (service/estimators/odom_drift.py)
and taken out of the odometry's turns (``OdomHeading.advance``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.engine.state_codec import dumps, loads
from service.estimators.odom_drift import DriftRate
from service.estimators.odometry import OdomHeading, OdomStep

STEP_M = 0.6
LOOK_SIGMA = math.radians(3.0)  # the located camera's yaw error, as in the rendered worlds


@pytest.mark.parametrize("drift_deg", [0.1, -0.1])
def test_the_drift_rate_is_found_from_noisy_located_yaws(drift_deg: float) -> None:
    rng = np.random.default_rng(5)
    d = DriftRate()
    drift = math.radians(drift_deg)
    for k in range(150):  # 90 m; the raw odometry's yaw turns `drift` too far per metre
        d.advance(STEP_M)
        d.look(0.4 - drift * STEP_M * (k + 1) + rng.normal(0.0, LOOK_SIGMA), LOOK_SIGMA)
    assert math.degrees(d.drift) == pytest.approx(drift_deg, abs=0.04)


def _drive(h: OdomHeading, rng: np.random.Generator, metres: float, look: bool,
           drift: bool) -> float:
    """Drive north (the map's heading pi/2) in odometry steps whose yaw drifts 0.1 deg/m
    counter-clockwise; located yaws (and positions) while ``look``; the heading error (rad)
    at the end."""
    for _ in range(round(metres / STEP_M)):
        h.advance(OdomStep(STEP_M, 0.0, math.radians(0.1) * STEP_M, 0.0, 1e-6))
        if look:
            h.look(math.pi / 2 + rng.normal(0.0, LOOK_SIGMA), LOOK_SIGMA, drift)
            h.observe(np.array([0.0, h.travelled]))
    heading, _ = h.heading(None)
    assert heading is not None
    return abs(math.remainder(heading - math.pi / 2, math.tau))


def test_the_corrected_odometry_holds_its_heading_where_nothing_is_located() -> None:
    """60 m located, then 40 m carried by the odometry alone: with the drift taken out the
    heading stays within a degree; without it, the 0.1 deg/m adds up to about 4 degrees."""
    errors = {}
    for drift in (True, False):
        h, rng = OdomHeading(), np.random.default_rng(3)
        _drive(h, rng, 60.0, True, drift)
        errors[drift] = math.degrees(_drive(h, rng, 40.0, False, drift))
    assert errors[True] < 1.0
    assert errors[False] > 3.0


def test_a_kidnap_keeps_the_rate_and_a_look_alike_yaw_is_left_out() -> None:
    d = DriftRate()
    for k in range(100):
        d.advance(STEP_M)
        d.look(-math.radians(0.1) * STEP_M * k, LOOK_SIGMA)
    rate = d.drift
    assert rate == pytest.approx(math.radians(0.1), abs=math.radians(0.02))
    assert d.x is not None
    offset = float(d.x[0])
    d.look(offset + math.radians(60.0), LOOK_SIGMA)  # a look-alike image: left out
    assert d.drift == rate and float(d.x[0]) == offset
    for _ in range(DriftRate.gate_frames - 1):  # the offset really moved (unseen by the
        d.look(offset + math.radians(60.0), LOOK_SIGMA)  # wheels): it restarts there
    assert d.x is not None and float(d.x[0]) == pytest.approx(offset + math.radians(60.0))
    assert d.drift == pytest.approx(rate)
    d.restart()  # a kidnap: the offset is unknown, the wheels' drift is not
    assert d.x is None and d.drift == pytest.approx(rate)


def test_a_heading_stored_before_the_drift_estimate_still_works() -> None:
    """A durable session written before the drift estimate: its OdomHeading has no
    ``drift`` or ``raw_yaw`` (the state codec sets only the stored attributes)."""
    old = OdomHeading()
    del old.drift, old.raw_yaw  # what that version stored
    back = loads(dumps({"h": old}))["h"]
    back.advance(OdomStep(1.0, 0.0, 0.1, 0.0, 0.0))
    back.look(0.5, LOOK_SIGMA, True)
    assert back.drift is not None and back.raw_yaw == pytest.approx(0.1)
    again = loads(dumps({"h": back}))["h"]  # and the drift estimate is stored with it
    assert again.drift is not None and np.array_equal(again.drift.x, back.drift.x)
    assert again.drift.rate == back.drift.rate and again.drift.gated == back.drift.gated
