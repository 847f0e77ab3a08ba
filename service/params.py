"""Estimator parameters with the papers' defaults, units and the choices where they are silent.

Reference: Kronfeld, Weiss, Zell, "Swarm-supported outdoor localization with sparse visual
data" (journal version), Sec. 4-5 and 7.2. The conference version's Tab. I gives v0 = 0.015
for the original speed, which fixes v0's unit: a fraction of the axis range per iteration.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Any, Literal, Self, get_args

#: DPSO variants (``service.registry`` dispatches each to its class)
DPSOVariant = Literal["swarmloc", "paper"]
DPSO_VARIANTS: tuple[str, ...] = get_args(DPSOVariant)


class ParamError(ValueError):
    """An unknown parameter name or an invalid value."""


@dataclass(frozen=True)
class _Params:
    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    def with_overrides(self, overrides: dict[str, Any] | None) -> Self:
        if not overrides:
            return self
        known = {f.name: f for f in fields(self)}
        unknown = sorted(set(overrides) - set(known))
        if unknown:
            raise ParamError(f"unknown parameter(s) {unknown}; known: {sorted(known)}")
        coerced = {}
        for k, v in overrides.items():
            typ = type(getattr(self, k))
            try:
                coerced[k] = typ(v)
            except (TypeError, ValueError):
                raise ParamError(f"parameter {k}={v!r} must be a {typ.__name__}") from None
        out = replace(self, **coerced)
        out.validate()
        return out

    def validate(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) and not math.isfinite(v):
                raise ParamError(f"parameter {f.name} must be finite")


@dataclass(frozen=True)
class CommonParams(_Params):
    """Fitness (Eq. 3) and lost detection, shared by all estimators."""

    # zeta in Eq. 3: Gaussian penalty of a particle's distance to its nearest map image. The
    # papers give no value; 2 m keeps full credit within the lateral spread of a street
    # (GPS noise, lane changes) and halves it ~2.4 m off the recorded path. Unit: metres.
    penalty_sigma_m: float = 2.0
    # "best match ... matching less than 5 % of local features" (Sec. 5). Unit: m in [0, 1].
    lost_threshold: float = 0.05
    # "several iterations in a row" (Sec. 5): 3 frames, long enough to ignore one blurred or
    # occluded frame, short enough to react within ~2 m at the papers' 0.6 m per frame.
    lost_frames: int = 3
    # frames of good matches in a row before "initializing" becomes "tracking"
    converge_frames: int = 3
    # frame interval assumed when frames carry no timestamps (s); the papers' 1 image/s
    default_dt_s: float = 1.0
    # EMA weight (journal footnote 1, alpha = 1/8) for the tracked velocity (speed, heading)
    # and the frame interval; DPSO's self-adaptation reads the same EMA
    ema_alpha: float = 0.125
    # initial placement (global start, our choice): particles around randomly drawn map
    # image positions with this spread (m) -- localisation is only possible near map images,
    # and uniform placement over the bounding box would waste most particles off the route.
    init_spread_m: float = 2.0

    def validate(self) -> None:
        super().validate()
        if self.penalty_sigma_m <= 0 or not 0 <= self.lost_threshold <= 1:
            raise ParamError("penalty_sigma_m must be > 0 and lost_threshold in [0, 1]")
        if self.lost_frames < 1 or self.converge_frames < 1 or self.default_dt_s <= 0:
            raise ParamError("lost_frames, converge_frames >= 1 and default_dt_s > 0 required")


@dataclass(frozen=True)
class DPSOParams(CommonParams):
    """Dynamic PSO, Eqs. 4-6 and the self-adaptation of Sec. 5."""

    n_particles: int = 80  # swarm size (Sec. 7.1)
    omega: float = 0.99  # inertia
    phi0: float = 0.3  # weight of the random perturbation
    phi2: float = 0.6  # attraction to the neighbourhood best p^n (star topology)
    # maximum velocity, fraction of the axis range per iteration; 0.015 is the conference
    # paper's manual setting for the original speed, the start value of the self-adaptation
    v0: float = 0.015
    v0_min: float = 0.001  # floor of the self-adaptation (our choice: never freeze the swarm)
    v0_max: float = 0.1  # recovery limit: "cross the search space in about 10 iterations"
    quantum_ratio: float = 0.1  # q_r, fraction of quantum particles (Eq. 6)
    quantum_ratio_max: float = 0.2  # recovery limit of q_r
    quantum_sigma: float = 0.15  # q_d, std of quantum particles, fraction of the axis range
    high_energy_ratio: float = 0.1  # h_r, particles allowed high_energy_factor * v0
    high_energy_factor: float = 3.0
    phi2_min: float = 0.01  # recovery limit of phi2
    adapt_low: float = 0.4  # keep EMA(v_sw) / v0 within [adapt_low, adapt_high] ...
    adapt_high: float = 0.6
    adapt_step: float = 0.1  # ... by changing v0 by 10 % per iteration
    # recovery raises v0 and q_r and lowers phi2 "towards" their limits (Sec. 5) by this
    # relative step per frame: v0 reaches v0_max ~5 frames after the loss. The paper gives no
    # rate; `swarmloc sweep` over 0.1 / 0.2 / 0.35 and `swarmloc experiment` on two worlds,
    # sunny and cloudy queries (README, "Choices measured"): 0.35 recovers from kidnapping
    # fastest; its cross-condition error is within run-to-run noise of 0.2 (5.1 vs 4.8 m)
    recovery_step: float = 0.35
    # good frames in a row that end the recovery phase ("as soon as the best matches increase
    # in quality again"), symmetric with lost_frames: with 1, one spurious match at the wrong
    # place ends the search and the ramp starts over. Measured with `swarmloc sweep`: 3 had
    # the faster kidnap recovery and lower cross-condition error averaged over two worlds
    recovered_frames: int = 3
    # smallest axis range used for delta_i (m): a straight route would otherwise have a zero
    # range across it and no lateral exploration at all
    min_axis_range_m: float = 20.0
    # ---- beyond the papers (service/multi_swarm.py; README "Localization across lighting")
    # "swarmloc": multi-swarm DPSO with motion prior, path evidence, scouts and relative lost
    # detection; "paper": the journal's DPSO as published (absolute 5 % trigger, one swarm)
    variant: str = "swarmloc"
    # carry particles by the tracked velocity while tracking: dropped (measured: the inertia
    # omega = 0.99 already carries the motion; both together overshoot, error x1.2-1.9)
    motion_prior: bool = False
    # attract each sub-swarm to where its seed will be at the next frame (seed + tracked step)
    predict_attractor: bool = False
    evidence_decay: float = 0.8  # lambda of A <- lambda A + f (about 5 frames of memory)
    species_radius_m: float = 5.0  # particles within this of a seed form its sub-swarm
    max_species: int = 4  # sub-swarms (hypotheses) at most
    dissolve_ratio: float = 0.5  # a sub-swarm below this share of the best one's support
    hypothesis_ratio: float = 0.1  # hypotheses reported down to this share of the best
    scout_ratio: float = 0.03  # particles redrawn at random map images every frame ...
    scout_ratio_recovery: float = 0.1  # ... and while recovering
    quantum_track_sigma_m: float = 2.0  # Eq. 6 spread while tracking (m); papers' q_d else
    distinct_ratio: float = 3.0  # best match / background for a frame to count as good
    distinct_floor_m: float = 0.004  # ... and at least this similarity (4 of 1,000 features)
    distinct_far_m: float = 10.0  # images farther than this from the best form the background
    estimate_radius_m: float = 2.5  # the estimate averages the best group within this (m)
    estimate_floor_m: float = 0.5  # std added to the estimate's covariance (m)
    # calibration: measured 67-70 % (seed 0) and 82 % (the test loop) of tracked frames
    # within accuracy_m at 0.6; 1.0 gave 79-98 %
    covariance_scale: float = 0.6
    # the estimate is the centre of the map images compared within this radius (m) of the
    # best group, weighted by m ** estimate_image_power: the place the images say, not where
    # the particles happen to be (README: same light 1.08-1.14 m -> 0.91 m)
    estimate_image_radius_m: float = 4.0
    estimate_image_power: float = 8.0
    # coasting: a frame whose best match is below coast_ratio x the level seen while tracking
    # is weak; through weak frames the tracked velocity is kept (not learnt from the weak
    # estimate) and the swarm is carried by it, for at most coast_max_frames frames
    coast_ratio: float = 0.65
    coast_max_frames: int = 30
    level_alpha: float = 0.1  # EMA weight of the tracking level of the best match

    def validate(self) -> None:
        super().validate()
        if self.n_particles < 2:
            raise ParamError("n_particles must be at least 2")
        for name in ("quantum_ratio", "quantum_ratio_max", "high_energy_ratio", "recovery_step"):
            if not 0 <= getattr(self, name) <= 1:
                raise ParamError(f"{name} must be in [0, 1]")
        if not 0 < self.v0_min <= self.v0 <= self.v0_max:
            raise ParamError("need 0 < v0_min <= v0 <= v0_max")
        if not 0 < self.adapt_low < self.adapt_high:
            raise ParamError("need 0 < adapt_low < adapt_high")
        if self.variant not in DPSO_VARIANTS:
            raise ParamError(f"variant must be one of {list(DPSO_VARIANTS)}")
        if not 0 <= self.evidence_decay < 1 or self.max_species < 1:
            raise ParamError("need 0 <= evidence_decay < 1 and max_species >= 1")
        if self.species_radius_m <= 0 or self.covariance_scale <= 0:
            raise ParamError("species_radius_m and covariance_scale must be > 0")
        for name in ("dissolve_ratio", "hypothesis_ratio", "scout_ratio", "scout_ratio_recovery"):
            if not 0 <= getattr(self, name) <= 1:
                raise ParamError(f"{name} must be in [0, 1]")
        for name in ("coast_ratio", "level_alpha"):
            if not 0 <= getattr(self, name) <= 1:
                raise ParamError(f"{name} must be in [0, 1]")
        if self.estimate_image_radius_m < 0 or self.estimate_image_power < 0 \
                or self.coast_max_frames < 0:
            raise ParamError("estimate_image_radius_m, estimate_image_power and "
                             "coast_max_frames must be >= 0")


@dataclass(frozen=True)
class PFParams(CommonParams):
    """Particle filter baselines (Sec. 7.2): PF-g (Gaussian motion) and PF-l (Eqs. 7-8)."""

    n_particles: int = 300
    sigma_gauss_m: float = 4.0  # PF-g motion noise per iteration (m)
    sigma_rot_deg: float = 60.0  # PF-l rotation noise per iteration
    sigma_acc: float = 1e-3  # PF-l log-speed noise per iteration
    v_init_mps: float = 2.0  # PF-l initial speed |v(0)| (m/s), about 3 v_R in the paper

    def validate(self) -> None:
        super().validate()
        if self.n_particles < 1 or self.sigma_gauss_m < 0 or self.sigma_rot_deg < 0:
            raise ParamError("n_particles >= 1 and non-negative noise levels required")
