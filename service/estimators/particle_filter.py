"""Particle filter baselines of journal Sec. 7.2.

PF-g: Gaussian motion model (sigma = 4 m per iteration). PF-l: linear motion, each particle's
velocity is rotated by N(0, sigma_rot) and scaled by exp(N(0, sigma_acc)) (Eqs. 7-8).
Importance weights are the fitness of Eq. 3; low-variance resampling every frame; the estimate
is the weighted mean.

With wheel odometry (beyond the papers) each particle also carries its own heading offset
between the odometry's frame and the map, as nav2's AMCL carries a yaw per particle: the
odometry's step moves a particle along its own offset, the offsets start uniform and take
the odometry's heading noise per step, and resampling keeps the offsets that stay on the
images. A single heading shared by every particle, fitted from the filter's own estimates,
moved the whole cloud off the route as soon as it was wrong (PF-l-300 with odometry: 12-64 m
mean error on a rendered world where it gives 1.0 m without). Like AMCL by default, the
filter injects no random particles: a kidnapped robot is not found again.
"""

from __future__ import annotations

import math

import numpy as np

from service.api.params import PFParams
from service.estimators.base import Estimator, Status, StepResult, weighted_covariance
from service.estimators.fitness import FrameFitness, MapIndex
from service.estimators.odometry import OdomStep

# position noise per metre travelled, per axis, beside the odometry's own: nav2 AMCL's default
# translation noise from translation (odom_alpha3 0.2); without it the cloud collapsed onto a
# place a few metres off and stayed there (PF-l-300 with odometry, data/w23's sunny2 round, six
# starts: 4.05 m mean error without this noise, 1.46 m with it)
ODOM_TRANSLATION_NOISE = 0.2


def low_variance_resample(rng: np.random.Generator, w: np.ndarray) -> np.ndarray:
    """Indices drawn by systematic (low-variance) resampling of normalised weights."""
    n = len(w)
    c = np.cumsum(w)
    c[-1] = 1.0
    u = rng.uniform(0.0, 1.0 / n) + np.arange(n) / n
    return np.searchsorted(c, u, side="left")


class ParticleFilter(Estimator):
    params: PFParams

    def __init__(self, index: MapIndex, params: PFParams, rng: np.random.Generator,
                 motion: str) -> None:
        super().__init__(index, params, rng)
        if motion not in ("gauss", "linear"):
            raise ValueError(f"unknown motion model {motion!r}")
        self.motion_model = motion
        self.name = "pf-g" if motion == "gauss" else "pf-l"
        self.x = np.zeros((params.n_particles, 2))
        self.v = np.zeros((params.n_particles, 2))
        # each particle's map yaw minus the odometry's yaw (rad); None until odometry moves
        # them (drawn then, so that a session without odometry draws nothing more)
        self.theta: np.ndarray | None = None

    def particles(self) -> np.ndarray | None:
        return None if self._needs_init else self.x

    def place(self, mask: np.ndarray, positions: np.ndarray) -> None:
        self.x[mask] = positions

    def _initialize(self) -> None:
        n = self.params.n_particles
        self.x = self.sample_positions(n)
        ang = self.rng.uniform(0, 2 * math.pi, n)
        self.v = self.params.v_init_mps * np.column_stack([np.cos(ang), np.sin(ang)])
        self.theta = None
        self.reset_motion()
        self._needs_init = False

    def _predict(self, dt: float) -> None:
        p, rng, n = self.params, self.rng, self.params.n_particles
        if self.motion_model == "gauss":
            self.x = self.x + rng.normal(0.0, p.sigma_gauss_m, (n, 2))
            return
        rot = rng.normal(0.0, math.radians(p.sigma_rot_deg), n)  # Eq. 7
        scale = np.exp(rng.normal(0.0, p.sigma_acc, n))
        c, s = np.cos(rot), np.sin(rot)
        vx, vy = self.v[:, 0], self.v[:, 1]
        self.v = scale[:, None] * np.column_stack([c * vx - s * vy, s * vx + c * vy])
        self.x = self.x + self.v * dt  # Eq. 8 (velocity in m/s, one frame interval)

    def _predict_odometry(self, odom: OdomStep) -> None:
        """The odometry motion model (Thrun et al., Probabilistic Robotics, Sec. 5.4), each
        particle with its own heading offset ``theta`` (the module's docstring): the step,
        taken in the odometry's frame at the previous dead-reckoned yaw, turned into the map
        by the particle's offset, with the step's noise and ``ODOM_TRANSLATION_NOISE`` of its
        length; the offsets walk by the odometry's heading noise over the step. The
        velocity that PF-l carries becomes the step per frame interval."""
        reckoning = self.dead_reckoning()
        yaw = float(reckoning.pose[2])  # before the step (drift-corrected)
        reckoning.advance(odom)  # the dead reckoning the heading output fits
        n, rng = self.params.n_particles, self.rng
        if self.theta is None:
            self.theta = rng.uniform(-math.pi, math.pi, n)
        walk = math.sqrt(max(odom.var_yaw * odom.distance, 0.0))
        if walk > 0:
            self.theta = self.theta + rng.normal(0.0, walk, n)
        a = self.theta + yaw
        c, s = np.cos(a), np.sin(a)
        d = np.column_stack([c * odom.forward - s * odom.left,
                             s * odom.forward + c * odom.left])
        spread = math.hypot(odom.sigma_xy, ODOM_TRANSLATION_NOISE * odom.distance)
        noise = rng.normal(0.0, spread, (n, 2)) if spread > 0 else 0.0
        self.x = self.x + d + noise
        if self.motion_model == "linear":
            self.v = d / (self._dt_ema or 1.0)

    def _step(self, fitness: FrameFitness, t: float | None, odom: OdomStep | None
              ) -> StepResult:
        dt = self.frame_dt(t)
        if self._needs_init:
            self._initialize()
        elif odom is not None:
            self._predict_odometry(odom)
        else:
            self._predict(dt)
        f, m, _ = fitness(self.x)
        total = f.sum()
        w = f / total if total > 0 else np.full(len(f), 1.0 / len(f))
        est = w @ self.x
        cov = weighted_covariance(self.x, w, 0.5 * self._spacing)
        spread = float(np.mean(np.linalg.norm(self.x - self.x.mean(axis=0), axis=1)))
        self.track_motion(est)
        status, lost = self.update_status(float(m.max()))
        idx = low_variance_resample(self.rng, w)
        self.x, self.v = self.x[idx], self.v[idx]
        if self.theta is not None:
            self.theta = self.theta[idx]
        speed, heading = self.motion(dt)
        self.odom_observe(odom, est, status is Status.TRACKING, lost)
        heading, source, h_sigma = self.odom_heading(odom, heading)
        return StepResult(est, cov, heading, speed, status, lost,
                          float(m.max()), fitness.comparisons, spread,
                          heading_source=source, heading_sigma=h_sigma)
