"""The wheel odometry's heading drift, estimated online from the located camera's yaw.

A robot's odometry turns a little too much or too little on every metre (a gyro's bias, the
wheels' unequal circumference): its dead-reckoned yaw drifts from the true one at a rate of
about a tenth of a degree per metre (the lab's worlds simulate 0.1 deg/m,
client/lab/world/rounds.py ``OdometryNoise``). Where the images locate the robot, the
camera's yaw in the map (service/vision/map_geometry.py) measures the offset between the
map's yaw and the raw dead-reckoned yaw; that offset changes with the travel at minus the
drift rate. ``DriftRate`` is a two-state Kalman filter over the travelled distance: the
offset and its rate of change, a random walk each, updated by every located yaw (an
innovation beyond ``gate_sigmas`` of its expected spread is a look-alike image and is left
out). The odometry's turn of each step is then corrected by the estimated drift before it
moves anything (``OdomHeading.advance``), so that a stretch the images cannot locate is
carried by a heading that no longer drifts.

The rate is a property of the robot, not of the place: a lost place keeps it. A jump the
wheels did not see (a kidnap, a frame without odometry) restarts the offset, never the rate.
"""

from __future__ import annotations

import math

import numpy as np

from service.api.geo import wrap_angle


class DriftRate:
    """The raw odometry's heading drift (rad per metre travelled) from located yaws."""

    # the rate's prior std (rad/m): a few tenths of a degree per metre
    prior_sigma = math.radians(0.2)
    # the offset's random walk between located yaws (rad^2 per metre): the odometry's own
    # per-step heading noise, far below the service's conservative odom_var_yaw
    walk_var = math.radians(0.2) ** 2
    # the rate's random walk (rad^2/m^2 per metre): a drift that changes slowly
    rate_walk_var = math.radians(0.002) ** 2
    gate_sigmas = 3.0  # innovations beyond this many stds are left out ...
    gate_frames = 5  # ... unless this many in a row are: then the offset restarts there
    limit = math.radians(1.0)  # the corrected drift is clipped to this (rad/m)

    def __init__(self) -> None:
        self.x: np.ndarray | None = None  # (offset rad, its change per metre rad/m)
        self.p = np.zeros((2, 2))  # their covariance
        self.rate = 0.0  # the drift kept through restarts (rad/m)
        self.rate_var = self.prior_sigma ** 2
        self.gated = 0  # located yaws left out in a row

    @property
    def drift(self) -> float:
        """The odometry's estimated heading drift (rad per metre; its yaw turns this much too
        far counter-clockwise per metre), clipped to ``limit``."""
        return float(np.clip(self.rate, -self.limit, self.limit))

    def advance(self, distance: float) -> None:
        """The odometry travelled ``distance`` m: the offset moves by the rate over it."""
        if self.x is None or distance <= 0:
            return
        f = np.array([[1.0, distance], [0.0, 1.0]])
        self.x = f @ self.x
        self.p = f @ self.p @ f.T + np.diag([self.walk_var * distance,
                                             self.rate_walk_var * distance])

    def look(self, offset: float, sigma: float) -> None:
        """A located yaw: ``offset`` = the camera's map yaw minus the raw dead-reckoned yaw
        (rad), with the camera yaw's std ``sigma`` (rad)."""
        r = sigma * sigma
        if self.x is None:
            self._start(offset, r)
            return
        innov = wrap_angle(offset - float(self.x[0]))
        s = float(self.p[0, 0]) + r
        if innov * innov > self.gate_sigmas ** 2 * s:
            self.gated += 1
            if self.gated >= self.gate_frames:  # the offset jumped (unseen by the wheels)
                self._start(offset, r)
            return
        self.gated = 0
        k = self.p[:, 0] / s  # the Kalman gain of a measurement of the offset alone
        x = self.x + k * innov
        self.x = np.array([wrap_angle(float(x[0])), float(x[1])])
        self.p = self.p - np.outer(k, self.p[0])
        self.rate, self.rate_var = -float(self.x[1]), float(self.p[1, 1])

    def _start(self, offset: float, r: float) -> None:
        """The offset starts at ``offset`` (variance ``r``); the rate is the one kept."""
        self.x = np.array([offset, -self.rate])
        self.p = np.diag([r, self.rate_var])
        self.gated = 0

    def restart(self) -> None:
        """A jump the wheels did not see: the offset is unknown again, the rate is kept."""
        self.x = None
