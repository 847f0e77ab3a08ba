"""What every estimator shares: initial placement, status bookkeeping, output of one step."""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from service.api.models import DEFAULT_PRIOR_RADIUS_M
from service.api.params import CommonParams
from service.estimators.fitness import (
    FrameFitness,
    LocateFn,
    MapIndex,
    NearestFn,
    SimilarityFn,
)
from service.estimators.jump_hold import off_prediction
from service.estimators.odometry import OdomHeading, OdomStep

# radius of the 68 % confidence disc of a 2-D Gaussian in units of sigma: sqrt(chi2_2(0.68))
_R68 = math.sqrt(-2.0 * math.log(1.0 - 0.68))


class EstimatorStateError(RuntimeError):
    """A step produced a non-finite state; the estimator re-initialised itself globally."""


def _check_finite(what: str, *values: float) -> None:
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{what} must be finite, got {values}")


class Status(StrEnum):
    INITIALIZING = "initializing"
    TRACKING = "tracking"
    # DPSO's recovery phase (boosted diversity), or a tracked frame whose two answers
    # disagree (the located camera far from the images' estimate, metric_disagree_m)
    RECOVERING = "recovering"
    LOST = "lost"  # bad matches for lost_frames in a row, no recovery mechanism (PF)


@dataclass(frozen=True)
class Hypothesis:
    """A competing position (m) with its share of the support of all hypotheses."""

    x: float
    y: float
    weight: float


@dataclass(frozen=True)
class StepResult:
    position: np.ndarray  # (2,) metres
    covariance: np.ndarray  # (2, 2) m^2
    heading: float  # radians, counter-clockwise from east (direction of motion)
    speed_mps: float
    status: Status
    lost: bool
    score: float  # best similarity m among the compared images
    comparisons: int  # distinct map images compared for this frame
    spread_m: float  # mean distance of particles to their centre (swarm diversity)
    hypotheses: tuple[Hypothesis, ...] = ()  # sub-swarms, best first (multi-swarm DPSO)
    # where the heading comes from: "motion" (direction of motion), "odometry" (the
    # odometry's yaw turned into the map, service/estimators/odometry.py) or "camera"
    heading_source: str = "motion"
    heading_sigma: float | None = None  # std of the heading, rad (None: not estimated)
    located: bool = False  # the frame was located by two-view geometry (multi-swarm DPSO)
    # reported recovering only because the geometry has not yet confirmed the place the
    # swarm tracks (multi-swarm DPSO's confirm_tracking): the swarm itself is tracking
    unconfirmed: bool = False

    @property
    def accuracy_m(self) -> float:
        """Radius of the 68 % horizontal confidence disc (ARCore Geospatial convention)."""
        return float(_R68 * math.sqrt(max(np.linalg.eigvalsh(self.covariance).max(), 0.0)))


def sigma_for_accuracy(accuracy_m: float) -> float:
    """The standard deviation per axis whose 68 % disc (``StepResult.accuracy_m``) has this
    radius."""
    return accuracy_m / _R68


def weighted_covariance(x: np.ndarray, w: np.ndarray, floor_m: float) -> np.ndarray:
    w = w / w.sum() if w.sum() > 0 else np.full(len(w), 1.0 / len(w))
    mu = w @ x
    d = x - mu
    cov = (d * w[:, None]).T @ d
    return cov + np.eye(2) * floor_m**2


class Estimator:
    """Base class: owns the generator, the placement of particles and the status machine."""

    name = "base"

    def __init__(self, index: MapIndex, params: CommonParams, rng: np.random.Generator) -> None:
        self.index = index
        self.params = params
        self.rng = rng
        pos = np.asarray(index.positions, float)
        self._map_positions = pos
        # map images sorted by x: the local scouts look up a band of x, not the whole map
        self._x_order = np.argsort(pos[:, 0], kind="stable")
        self._x_sorted = pos[self._x_order, 0]
        self._spacing = float(np.median(np.linalg.norm(np.diff(pos, axis=0), axis=1))) \
            if len(pos) > 1 else 1.0
        self._init_near: tuple[np.ndarray, float] | None = None
        # candidate places (k, 2) of this frame from the map's place index (PlaceSeeder);
        # None: random placements are drawn around random map images
        self.place_candidates: np.ndarray | None = None
        # the place seeder's checks while tracking (kept here, with the estimator's state,
        # so that a session moved between replicas continues identically)
        self.place_frames = 0  # tracked frames seen by the seeder
        self.place_disagree = 0  # periodic index checks in a row that disagreed
        self._needs_init = True
        self._bad = 0
        self._good = 0
        self._converged = False
        self._last_t: float | None = None
        self._dt_ema: float | None = None
        # the map heading from wheel odometry: made by the first odometry step (a session
        # without odometry stores nothing of it)
        self.odometry: OdomHeading | None = None
        self.reset_motion()

    # ---- placement ----------------------------------------------------------------------
    @property
    def spacing(self) -> float:
        """The map's median distance between consecutive images: the scale of its path."""
        return self._spacing

    def reset(self, near: tuple[float, float] | None = None, radius: float | None = None) -> None:
        """Global re-initialisation, or around a known pose (like AMCL's initial pose)."""
        if near is not None:
            r = float(radius) if radius is not None else DEFAULT_PRIOR_RADIUS_M
            _check_finite("reset pose and radius", float(near[0]), float(near[1]), r)
            self._init_near = (np.asarray(near, float), max(r, 0.0))
        else:
            self._init_near = None
        self._needs_init = True
        self._bad = self._good = 0
        self._converged = False
        self._last_t = None
        self._dt_ema = None
        self.odometry = None
        self.reset_motion()

    def sample_positions(self, n: int) -> np.ndarray:
        if self._init_near is not None:
            c, r = self._init_near
            return disc_sample(self.rng, c, r, n)
        return self.sample_map_positions(n)

    def sample_map_positions(self, n: int) -> np.ndarray:
        """Positions around randomly drawn map images (localisation needs a map image near),
        or around this frame's candidate places from the place index when it gave some."""
        pool = self.place_candidates if self.place_candidates is not None and \
            len(self.place_candidates) else self._map_positions
        ids = self.rng.integers(0, len(pool), n)
        return pool[ids] + self.rng.normal(0, self.params.init_spread_m, (n, 2))

    def wants_places(self) -> bool:
        """Whether the place index should seed this frame's random placements: before the
        first placement, until converged, while lost or recovering."""
        return (self._needs_init or not self._converged or self._bad >= self.params.lost_frames
                or bool(getattr(self, "recovering", False)))

    def sample_map_positions_near(self, centre: np.ndarray, inner: float, outer: float, n: int
                                  ) -> np.ndarray:
        """Positions around map images drawn among those between ``inner`` and ``outer``
        metres of ``centre`` (the nearest image where none is)."""
        lo = int(np.searchsorted(self._x_sorted, centre[0] - outer, "left"))
        hi = int(np.searchsorted(self._x_sorted, centre[0] + outer, "right"))
        band = np.sort(self._x_order[lo:hi])  # ascending ids, as a scan of the map gives
        d = np.linalg.norm(self._map_positions[band] - centre, axis=1)
        near = band[(d >= inner) & (d <= outer)]
        if not len(near):
            near = self.index.nearest(np.asarray(centre, float)[None, :])[0][:1]
        ids = near[self.rng.integers(0, len(near), n)]
        return self._map_positions[ids] + self.rng.normal(0, self.params.init_spread_m, (n, 2))

    def constrain(self, center: tuple[float, float], radius: float) -> None:
        """A pose prior for this frame: particles outside the disc are redrawn inside it."""
        _check_finite("pose prior and radius", float(center[0]), float(center[1]),
                      float(radius))
        x = self.particles()
        if x is None:
            self.reset(center, radius)
            return
        c = np.asarray(center, float)
        outside = np.linalg.norm(x - c, axis=1) > radius
        if outside.any():
            self.place(outside, disc_sample(self.rng, c, radius, int(outside.sum())))

    def particles(self) -> np.ndarray | None:
        raise NotImplementedError

    def place(self, mask: np.ndarray, positions: np.ndarray) -> None:
        raise NotImplementedError

    # ---- one frame ----------------------------------------------------------------------
    def frame_dt(self, t: float | None) -> float:
        """Seconds since the previous frame (EMA-smoothed); default_dt_s without timestamps."""
        dt = self.params.default_dt_s
        if t is not None and self._last_t is not None and t > self._last_t:
            dt = t - self._last_t
        self._last_t = t if t is not None else None
        a = self.params.ema_alpha
        self._dt_ema = dt if self._dt_ema is None else (1 - a) * self._dt_ema + a * dt
        return dt

    # ---- motion (speed and heading) -----------------------------------------------------
    def reset_motion(self) -> None:
        self._point_prev: np.ndarray | None = None
        self.ema_step: np.ndarray | None = None  # metres per frame, vector

    def track_motion(self, point: np.ndarray, learn: bool = True,
                     predicted: np.ndarray | None = None, jump_m: float = 0.0) -> None:
        """EMA (alpha = ema_alpha) of the per-frame displacement of the tracked point.

        The EMA runs over the displacement *vector*, so jitter of the point averages out
        instead of adding to the speed (an EMA of its norm would be biased upwards). With
        ``learn=False`` the point only becomes the reference of the next displacement and the
        velocity is kept (a frame whose estimate says nothing about the motion). A
        displacement farther than ``jump_m`` (> 0) from the ``predicted`` step (none: no
        step) is a jump between places, not motion: it does not teach the velocity either.
        """
        if learn and self._point_prev is not None:
            d = point - self._point_prev
            if jump_m <= 0 or off_prediction(self._point_prev, point, predicted) <= jump_m:
                a = self.params.ema_alpha
                self.ema_step = d.copy() if self.ema_step is None \
                    else (1 - a) * self.ema_step + a * d
        self._point_prev = np.array(point, float)

    def motion(self, dt: float) -> tuple[float, float]:
        """(speed m/s, heading rad) of the tracked point."""
        if self.ema_step is None:
            return 0.0, 0.0
        speed = float(np.linalg.norm(self.ema_step)) / (self._dt_ema or dt)
        return speed, math.atan2(self.ema_step[1], self.ema_step[0])

    # ---- odometry (service/estimators/odometry.py) -------------------------------------
    def odom_move(self, odom: OdomStep) -> tuple[np.ndarray, float]:
        """The odometry step in the map frame (m) and the std (m, per axis) of where it
        ends, turned by the map heading at the previous frame; advances the dead reckoning."""
        motion_heading = self.motion(1.0)[1] if self.ema_step is not None else None
        reckoning = self.dead_reckoning()
        d, sigma = reckoning.displacement(odom, motion_heading)
        reckoning.advance(odom)
        return d, sigma

    def dead_reckoning(self) -> OdomHeading:
        """The session's integrated odometry and its map heading (started at the first
        odometry step)."""
        if self.odometry is None:
            self.odometry = OdomHeading()
        return self.odometry

    def odom_observe(self, odom: OdomStep | None, xy: np.ndarray, trusted: bool,
                     lost: bool) -> None:
        """After a frame: an image estimate ``trusted`` to be the place teaches the map
        heading; a lost place, or a frame without odometry, forgets the pairs (they may
        belong to a wrong place, or the dead reckoning missed a step)."""
        if self.odometry is None:
            return
        if odom is None or lost:
            if len(self.odometry.pairs):
                self.odometry.forget()
            return
        if trusted:
            self.odometry.observe(xy)

    def odom_heading(self, odom: OdomStep | None, heading: float
                     ) -> tuple[float, str, float | None]:
        """(heading, its source, its std): the odometry's where it has a map heading, the
        direction of motion ``heading`` otherwise."""
        if odom is not None and self.odometry is not None and self.odometry.offset is not None:
            h, sigma = self.odometry.heading(None)
            assert h is not None
            return h, "odometry", sigma
        return heading, "motion", None

    def update_status(self, best_m: float) -> tuple[Status, bool]:
        p = self.params
        if best_m < p.lost_threshold:
            self._bad += 1
            self._good = 0
        else:
            self._bad = 0
            self._good += 1
        if self._good >= p.converge_frames:
            self._converged = True
        lost = self._bad >= p.lost_frames
        if lost:
            return Status.LOST, True
        return (Status.TRACKING if self._converged else Status.INITIALIZING), False

    def step(self, similarity: SimilarityFn, t: float | None = None,
             locate: LocateFn | None = None, odom: OdomStep | None = None,
             nearest: NearestFn | None = None, first: SimilarityFn | None = None
             ) -> StepResult:
        """One frame: ``similarity`` compares it with map images; ``locate``, where given,
        places its camera relative to one (two-view geometry, for an estimator that uses
        it); ``odom``, where given, is the robot's motion since the previous frame;
        ``nearest``, where given, names the images each particle is compared with (default:
        the nearest of every layer); ``first``, on a map of two feature types, the first
        type's own m of the images ``similarity`` compared (``fitness.TypeScores``)."""
        fitness = FrameFitness(self.index, similarity, self.params.penalty_sigma_m, locate,
                               nearest, first)
        try:
            result = self._step(fitness, t, odom)
        except ValueError:  # e.g. a KD-tree query refusing non-finite particles
            if self._particles_finite():
                raise
            result = None
        self.check_invariant(result)
        assert result is not None
        return result

    def _particles_finite(self) -> bool:
        x = self.particles()
        return x is None or bool(np.isfinite(x).all())

    def check_invariant(self, result: StepResult | None) -> None:
        """The state stays finite: after a step whose particles or result are not, the
        estimator re-initialises globally and raises EstimatorStateError, so the next frame
        starts from a valid state instead of failing for good."""
        ok = result is not None and self._particles_finite() and bool(
            np.isfinite(result.position).all() and np.isfinite(result.covariance).all()
            and math.isfinite(result.speed_mps) and math.isfinite(result.heading))
        if not ok:
            self.reset()
            raise EstimatorStateError("the estimator's state became non-finite; it was "
                                      "re-initialised (global placement)")

    def _step(self, fitness: FrameFitness, t: float | None, odom: OdomStep | None
              ) -> StepResult:
        raise NotImplementedError


def disc_sample(rng: np.random.Generator, c: np.ndarray, r: float, n: int) -> np.ndarray:
    ang = rng.uniform(0, 2 * np.pi, n)
    rad = r * np.sqrt(rng.uniform(0, 1, n))
    return c + np.column_stack([rad * np.cos(ang), rad * np.sin(ang)])
