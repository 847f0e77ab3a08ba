"""Dynamic Particle Swarm Optimization (DPSO), journal Sec. 5.

Per frame: evaluate Eq. 3 at every particle, take the best particle p^n (star topology) as the
estimate, adapt v0 from the swarm-centre speed, run the recovery state machine, then move the
swarm for the next frame with Eqs. 4-5 (normal and high-energy particles) and Eq. 6 (quantum
particles). Positions are metres; delta_i is the map's range along axis i.
"""

from __future__ import annotations

import math

import numpy as np

from service.api.params import DPSOParams
from service.estimators.base import Estimator, Status, StepResult, weighted_covariance
from service.estimators.fitness import FrameFitness, MapIndex
from service.estimators.odometry import OdomStep


class DPSO(Estimator):
    name = "dpso"
    params: DPSOParams

    def __init__(self, index: MapIndex, params: DPSOParams, rng: np.random.Generator) -> None:
        super().__init__(index, params, rng)
        pos = np.asarray(index.positions, float)
        # delta_i: range of axis i (m), floored so that a straight route still has a width
        span = np.maximum(pos.max(axis=0) - pos.min(axis=0), params.min_axis_range_m)
        # ... and capped, so that the swarm's steps stay street-sized on a city-sized map
        # (the place index, not the velocity, makes the long jumps there)
        self.delta = np.minimum(span, params.max_axis_range_m)
        n = params.n_particles
        # search space: the map's bounding box, widened by 10 % of each range; particles
        # reflect at its walls (standard PSO boundary handling, not spelled out in the paper)
        self.lower = pos.min(axis=0) - 0.1 * span
        self.upper = pos.max(axis=0) + 0.1 * span
        # particle types are fixed subsets, as in the quantum swarms of Blackwell & Branke
        # (the paper's ref. [32]): the last h_r * n are high-energy, the first q_r * n quantum
        # (see _move; recovery grows the quantum subset towards quantum_ratio_max)
        self.high_energy = np.arange(n) >= n - round(params.high_energy_ratio * n)
        self.x = np.zeros((n, 2))
        self.v = np.zeros((n, 2))
        self._init_adaptive()

    def _init_adaptive(self) -> None:
        p = self.params
        self.v0, self.q_r, self.phi2 = self.start_v0(), p.quantum_ratio, p.phi2
        self.recovering = False
        self._v0_before_recovery = self.v0
        self.reset_motion()

    def start_v0(self) -> float:
        """v0 at the start (and after a reset): the papers' ``v0``."""
        return self.params.v0

    def particles(self) -> np.ndarray | None:
        return None if self._needs_init else self.x

    def place(self, mask: np.ndarray, positions: np.ndarray) -> None:
        self.x[mask] = positions
        self.v[mask] = 0.0

    def _initialize(self) -> None:
        p = self.params
        n = p.n_particles
        self.x = self.sample_positions(n)
        ang = self.rng.uniform(0, 2 * math.pi, n)
        mag = self.rng.uniform(0, 1, n) * self.start_v0()
        self.v = np.column_stack([np.cos(ang), np.sin(ang)]) * mag[:, None] * self.delta
        self._init_adaptive()
        self._needs_init = False

    def _step(self, fitness: FrameFitness, t: float | None, odom: OdomStep | None
              ) -> StepResult:
        if self._needs_init:
            self._initialize()
        dt = self.frame_dt(t)
        if odom is not None:  # the swarm (and with it p^n's neighbourhood) moves with the robot
            self.move_by_odometry(odom)
        f, m, _ = fitness(self.x)
        best = int(np.argmax(f))
        p_n = self.x[best].copy()
        best_m = float(m.max())
        cov = weighted_covariance(self.x, f, 0.5 * self._spacing)
        centre = self.x.mean(axis=0)
        spread = float(np.mean(np.linalg.norm(self.x - centre, axis=1)))
        # v_sw: speed of the swarm's centre of mass, the masses being the fitness (the
        # "weighted swarm center" of Sec. 4). Quantum particles are redrawn around p^n with
        # q_d = 15 % of the range every frame; in an unweighted centre that alone moves the
        # centre by about a metre per frame.
        total = float(f.sum())
        self.track_motion((f @ self.x) / total if total > 0 else centre)

        status, lost = self.update_status(best_m)
        if self.recovery_phase(lost):
            status = Status.RECOVERING
        self._move(p_n)
        speed, heading = self.motion(dt)
        self.odom_observe(odom, p_n, status is Status.TRACKING, lost or self.recovering)
        heading, source, h_sigma = self.odom_heading(odom, heading)
        return StepResult(p_n, cov, heading, speed, status, lost, best_m, fitness.comparisons,
                          spread, heading_source=source, heading_sigma=h_sigma)

    def move_by_odometry(self, odom: OdomStep) -> None:
        """Every particle moves by the odometry step turned into the map, plus its noise
        (service/estimators/odometry.py); the walls of the search space clip them."""
        d, sigma = self.odom_move(odom)
        noise = self.rng.normal(0.0, sigma, self.x.shape) if sigma > 0 else 0.0
        self.x = np.clip(self.x + d + noise, self.lower, self.upper)

    def recovery_phase(self, lost: bool) -> bool:
        """Sec. 5's recovery state machine; True while recovering. Entering it keeps v0;
        ``recovered_frames`` good frames restore v0, q_r and phi2; while it lasts, diversity
        is boosted step by step towards the limits, otherwise v0 self-adapts."""
        p = self.params
        if lost and not self.recovering:  # recovery phase starts
            self.recovering = True
            self._v0_before_recovery = self.v0
        elif self.recovering and self._good >= p.recovered_frames:  # matches are good again
            self.recovering = False
            self.v0, self.q_r, self.phi2 = self._v0_before_recovery, p.quantum_ratio, p.phi2
        if self.recovering:
            a = p.recovery_step
            self.v0 = min(self.v0 * (1 + a), p.v0_max)
            self.q_r = min(self.q_r * (1 + a), p.quantum_ratio_max)
            self.phi2 = max(self.phi2 * (1 - a), p.phi2_min)
        else:
            self._adapt_v0()
        return self.recovering

    def _adapt_v0(self) -> None:
        """Hold v0 ~ 2 v_sw: change v0 by 10 % when EMA(v_sw) / v0 leaves [0.4, 0.6]."""
        p = self.params
        if self.ema_step is None:
            return
        v_sw = float(np.linalg.norm(self.ema_step / self.delta))  # axis-range units per frame
        ratio = v_sw / self.v0
        if ratio < p.adapt_low:
            self.v0 *= 1 - p.adapt_step
        elif ratio > p.adapt_high:
            self.v0 *= 1 + p.adapt_step
        self.v0 = float(np.clip(self.v0, p.v0_min, p.v0_max))

    def _move(self, p_n: np.ndarray) -> None:
        p, rng = self.params, self.rng
        n = p.n_particles
        # symmetric perturbation (docs/reference/estimators.md: r0 range)
        r0 = rng.uniform(-1.0, 1.0, (n, 2))
        r2 = rng.uniform(0.0, 1.0, (n, 2))
        # Eq. 4
        v = p.omega * self.v + p.phi0 * r0 * self.delta * self.v0 + self.phi2 * r2 * (p_n - self.x)
        norm = np.linalg.norm(v / self.delta, axis=1)
        limit = self.v0 * np.where(self.high_energy, p.high_energy_factor, 1.0)
        v *= np.minimum(1.0, limit / np.maximum(norm, 1e-12))[:, None]
        x = self.x + v  # Eq. 5
        # Eq. 6: the quantum particles are redrawn around p^n and have no speed
        k = min(round(self.q_r * n), n - int(self.high_energy.sum()))
        x[:k] = p_n + self.delta * rng.normal(0.0, p.quantum_sigma, (k, 2))
        v[:k] = 0.0
        # reflect at the walls of the search space
        below, above = x < self.lower, x > self.upper
        x = np.where(below, 2 * self.lower - x, np.where(above, 2 * self.upper - x, x))
        x = np.clip(x, self.lower, self.upper)
        v = np.where(below | above, -v, v)
        self.x, self.v = x, v
