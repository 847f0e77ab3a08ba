"""Estimator parameters with the papers' defaults, units and the choices where they are silent.

Reference: Kronfeld, Weiss, Zell, "Swarm-supported outdoor localization with sparse visual
data" (journal version), Sec. 4-5 and 7.2. The conference version's Tab. I gives v0 = 0.015
for the original speed, which fixes v0's unit: a fraction of the axis range per iteration.

The parameter sets are pydantic models: strict types (``n_particles: 2.9`` is refused, not
truncated), finite numbers only, documented bounds and no unknown names. The same models
validate overrides from every transport and appear in the OpenAPI schema, so HTTP and Zenoh
give the same 422 message for the same bad value.
"""

from __future__ import annotations

from typing import Any, Literal, Self, get_args

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from service.api.errors import describe_errors

# the most particles any estimator accepts (a per-service ceiling below this is the setting
# SWARMLOC_MAX_PARTICLES): 1e5 particles already take seconds per frame on one core
MAX_PARTICLES = 100_000

#: DPSO variants (``service.estimators.registry`` dispatches each to its class)
DPSOVariant = Literal["swarmloc", "paper"]
DPSO_VARIANTS: tuple[str, ...] = get_args(DPSOVariant)


class ParamError(ValueError):
    """An unknown parameter name or an invalid value."""


class _Params(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", strict=True, allow_inf_nan=False,
                              validate_default=False)

    def as_dict(self) -> dict[str, Any]:
        return self.model_dump()

    def with_overrides(self, overrides: dict[str, Any] | None) -> Self:
        """A copy with ``overrides`` applied and validated (raises ParamError)."""
        if not overrides:
            return self
        if not isinstance(overrides, dict):
            raise ParamError("params must be a JSON object of name: value")
        known = set(type(self).model_fields)
        unknown = sorted(set(overrides) - known)
        if unknown:
            raise ParamError(f"unknown parameter(s) {unknown}; known: {sorted(known)}")
        try:
            return type(self).model_validate({**self.model_dump(), **overrides})
        except ValidationError as exc:
            raise ParamError("invalid parameter: " + describe_errors(exc.errors())) from None


def _check(ok: bool, message: str) -> None:
    if not ok:
        raise ValueError(message)


class CommonParams(_Params):
    """Fitness (Eq. 3) and lost detection, shared by all estimators."""

    penalty_sigma_m: float = Field(
        2.0, gt=0, le=1000, description="zeta in Eq. 3 (m): Gaussian penalty of a particle's "
        "distance to its nearest map image. The papers give no value; 2 m keeps full credit "
        "within the lateral spread of a street (GPS noise, lane changes) and halves it ~2.4 m "
        "off the recorded path")
    lost_threshold: float = Field(
        0.05, ge=0, le=1, description="best match below this similarity m counts as bad: "
        "'matching less than 5 % of local features' (Sec. 5)")
    lost_frames: int = Field(
        3, ge=1, le=1000, description="bad frames in a row before 'lost' ('several iterations "
        "in a row', Sec. 5): ignores one blurred frame, reacts within ~2 m at 0.6 m/frame")
    converge_frames: int = Field(
        3, ge=1, le=1000, description="good frames in a row before 'initializing' becomes "
        "'tracking'")
    default_dt_s: float = Field(
        1.0, gt=0, le=3600, description="frame interval (s) assumed when frames carry no "
        "timestamps; the papers' 1 image/s")
    ema_alpha: float = Field(
        0.125, gt=0, le=1, description="EMA weight (journal footnote 1, alpha = 1/8) of the "
        "tracked velocity and the frame interval; DPSO's self-adaptation reads the same EMA")
    init_spread_m: float = Field(
        2.0, ge=0, le=1000, description="global start (m): particles are placed around "
        "randomly drawn map images with this spread; localisation is only possible near map "
        "images, uniform placement would waste most particles off the route")


class DPSOParams(CommonParams):
    """Dynamic PSO, Eqs. 4-6 and the self-adaptation of Sec. 5, plus the multi-swarm
    extensions of service/estimators/multi_swarm_dpso.py (README "Localization across lighting")."""

    n_particles: int = Field(80, ge=2, le=MAX_PARTICLES,
                             description="swarm size (Sec. 7.1); cost per frame grows with it")
    omega: float = Field(0.99, ge=0, le=2, description="inertia (Eq. 4)")
    phi0: float = Field(0.3, ge=0, le=10, description="weight of the random perturbation")
    phi2: float = Field(0.6, ge=0, le=10, description="attraction to the neighbourhood best "
                        "p^n (star topology)")
    v0: float = Field(0.015, gt=0, le=1, description="maximum velocity, fraction of the axis "
                      "range per iteration; the conference paper's manual setting for the "
                      "original speed and the start value of the self-adaptation")
    v0_min: float = Field(0.001, gt=0, le=1, description="floor of the self-adaptation (our "
                          "choice: never freeze the swarm)")
    v0_max: float = Field(0.1, gt=0, le=1, description="recovery limit: 'cross the search "
                          "space in about 10 iterations'")
    quantum_ratio: float = Field(0.1, ge=0, le=1, description="q_r, share of quantum "
                                 "particles (Eq. 6)")
    quantum_ratio_max: float = Field(0.2, ge=0, le=1, description="recovery limit of q_r")
    quantum_sigma: float = Field(0.15, ge=0, le=10, description="q_d, std of quantum "
                                 "particles, fraction of the axis range")
    high_energy_ratio: float = Field(0.1, ge=0, le=1, description="h_r, share of particles "
                                     "allowed high_energy_factor * v0")
    high_energy_factor: float = Field(3.0, ge=0, le=100, description="speed factor of the "
                                      "high-energy particles")
    phi2_min: float = Field(0.01, ge=0, le=10, description="recovery limit of phi2")
    adapt_low: float = Field(0.4, gt=0, le=10, description="keep EMA(v_sw) / v0 within "
                             "[adapt_low, adapt_high] ...")
    adapt_high: float = Field(0.6, gt=0, le=10, description="... upper end of that band")
    adapt_step: float = Field(0.1, ge=0, le=1, description="... by changing v0 by this "
                              "share per iteration")
    recovery_step: float = Field(
        0.35, ge=0, le=1, description="relative step per frame by which recovery raises v0 "
        "and q_r and lowers phi2 towards their limits (Sec. 5 gives no rate); 0.35 recovered "
        "from kidnapping fastest in `swarmloc sweep` (README, 'Choices measured')")
    recovered_frames: int = Field(
        3, ge=1, le=1000, description="good frames in a row that end the recovery phase, "
        "symmetric with lost_frames; 3 measured best with `swarmloc sweep`")
    min_axis_range_m: float = Field(
        20.0, gt=0, le=1e6, description="smallest axis range used for delta_i (m): a "
        "straight route would otherwise have no lateral exploration")
    place_candidates: int = Field(
        10, ge=0, le=1000, description="while searching (global start, not yet converged, "
        "lost or recovering), random placements are drawn around the top-k images of the "
        "map's place index for the frame instead of random map images (service/"
        "place_index.py); 0, or a map without an index: random map images. The papers' "
        "estimators (variant 'paper', the particle filters) always use random images")
    max_axis_range_m: float = Field(
        200.0, gt=0, le=1e7, description="largest axis range used for delta_i (m): on a "
        "map wider than a district the swarm's velocities, perturbation and recovery spread "
        "(fractions of delta_i) would grow with the map (more comparisons per frame, slower "
        "to settle); long jumps come from the place index instead. The papers' routes "
        "(< 200 m per axis) are unaffected")
    variant: DPSOVariant = Field(
        "swarmloc", description="'swarmloc': multi-swarm DPSO with path evidence, scouts and "
        "relative lost detection; 'paper': the journal's DPSO as published")
    motion_prior: bool = Field(
        False, description="carry particles by the tracked velocity while tracking (dropped: "
        "with omega = 0.99 both together overshoot, error x1.2-1.9)")
    predict_attractor: bool = Field(
        False, description="attract each sub-swarm to where its seed will be at the next "
        "frame (seed + tracked step), so the swarm does not trail a robot that moves about "
        "an image spacing per frame (KITTI even/odd over 5 seeds 0.51 / 0.36 -> 0.17 / "
        "0.20 m, four worlds x 3 conditions summed 17.57 -> 17.17 m); off by default: it "
        "loses on the second cloudy day (1.21 -> 1.27 m over 12 starts)")
    evidence_decay: float = Field(0.8, ge=0, lt=1, description="lambda of A <- lambda A + f "
                                  "(about 5 frames of memory)")
    species_radius_m: float = Field(5.0, gt=0, le=1e4, description="particles within this "
                                    "of a seed form its sub-swarm (m)")
    max_species: int = Field(4, ge=1, le=64, description="sub-swarms (hypotheses) at most")
    dissolve_ratio: float = Field(0.5, ge=0, le=1, description="a sub-swarm below this share "
                                  "of the best one's support dissolves")
    dissolve_mean_ratio: float = Field(
        1.0, ge=0, le=100, description="... unless the mean evidence along its particles' "
        "paths is at least this share of the best one's: a young sub-swarm that is better "
        "per frame survives (a scout that found the true place has one frame of evidence "
        "against the incumbent's five). Across light over four worlds, summed over eight "
        "cases, 14.95 -> 13.24 m; 0: the sum alone")
    hypothesis_ratio: float = Field(0.1, ge=0, le=1, description="hypotheses are reported "
                                    "down to this share of the best")
    scout_ratio: float = Field(0.03, ge=0, le=1, description="share of particles redrawn at "
                               "random map images every frame ...")
    scout_ratio_recovery: float = Field(0.1, ge=0, le=1, description="... and while "
                                        "recovering")
    quantum_track_sigma_m: float = Field(2.0, ge=0, le=1e4, description="Eq. 6 spread while "
                                         "tracking (m); the papers' q_d otherwise")
    distinct_ratio: float = Field(3.0, ge=0, le=1e3, description="best match / background "
                                  "for a frame to count as good")
    distinct_floor_m: float = Field(0.004, ge=0, le=1, description="... and at least this "
                                    "similarity (4 of 1,000 features)")
    distinct_far_m: float = Field(10.0, ge=0, le=1e5, description="images farther than this "
                                  "from the best form the background (m)")
    estimate_radius_m: float = Field(2.5, gt=0, le=1e4, description="the estimate averages "
                                     "the best group within this (m)")
    estimate_floor_m: float = Field(0.5, ge=0, le=1e4, description="std added to the "
                                    "estimate's covariance (m)")
    covariance_scale: float = Field(
        0.1, gt=0, le=100, description="scale of the best sub-swarm's covariance in the "
        "estimate's covariance (calibration, with match_sigma_m and lateral_sigma_m)")
    match_sigma_m: float = Field(
        0.375, ge=0, le=1e3, description="std (m) added to the estimate for its match "
        "strength: match_sigma_m * m_best ** -match_sigma_power (0.75 m at m = 0.06, 1.1 m "
        "at m = 0.015): weak matches place the robot less sharply")
    lateral_sigma_m: float = Field(
        0.6, ge=0, le=1e3, description="std (m) added for the robot's offset from the "
        "recorded path, which images along one path cannot tell (two traversals of a street "
        "differ by a lane position; the synthetic world's rounds by 0-1.2 m)")
    match_sigma_power: float = Field(
        0.25, ge=0, le=4, description="exponent of that std's dependence on m_best")
    estimate_image_radius_m: float = Field(
        4.0, ge=0, le=1e4, description="the estimate is the centre of the map images compared "
        "within this radius (m) of the best group, weighted by m ** estimate_image_power: the "
        "place the images say, not where the particles happen to be (same light 1.08-1.14 m "
        "-> 0.91 m; 0 switches it off)")
    estimate_image_power: float = Field(
        8.0, ge=0, le=64, description="exponent of the similarity weights of that centre")
    coast_ratio: float = Field(
        0.65, ge=0, le=1, description="a frame whose best match is below this share of the "
        "level seen while tracking is weak: through weak frames the tracked velocity is kept "
        "and the swarm carried by it (0 switches coasting off)")
    coast_max_frames: int = Field(
        30, ge=0, le=100_000, description="weak frames in a row coasted through at most")
    level_alpha: float = Field(
        0.1, ge=0, le=1, description="EMA weight of the tracking level of the best match")
    local_scout_ratio: float = Field(
        0.1, ge=0, le=1, description="share of particles redrawn at map images between "
        "local_scout_inner_m and local_scout_radius_m of the estimate every "
        "local_scout_every-th frame while tracking: the local search a particle filter's "
        "motion noise gives, so a swarm that stalls (the robot started off after a stop, "
        "the estimate kept still) finds the robot that moved on (across light 1.48 / 1.43 m "
        "-> 1.23 / 1.31 m; 0 switches it off)")
    local_scout_radius_m: float = Field(
        15.0, ge=0, le=1e5, description="outer radius of the local scouts (m)")
    local_scout_inner_m: float = Field(
        4.0, ge=0, le=1e5, description="inner radius of the local scouts (m): the images "
        "nearer are compared by the swarm and the estimate already")
    local_scout_every: int = Field(
        2, ge=1, le=1000, description="local scouts every this many frames (a stall grows "
        "over tens of frames; every 2nd frame halves their comparisons)")
    along_track_alpha: float = Field(
        0.7, gt=0, le=1, description="share of the along-path correction the reported "
        "position takes each tracked frame (service/estimators/along_track.py; across the path it "
        "takes all of it; its velocity takes alpha^2 / (2 - alpha), Benedict-Bordner). "
        "Across light over four worlds 1.21 / 1.29 / 1.18 / 1.98 m -> 1.19 / 1.26 / 1.16 / "
        "1.96 m, KITTI even/odd over 5 seeds 0.55 / 0.40 -> 0.51 / 0.36 m; 1 switches it off")
    along_track_alpha_unlocated: float = Field(
        0.35, gt=0, le=1, description="along_track_alpha for a tracked frame the geometry "
        "ran on but could not locate (a map with the camera's intrinsics): its image "
        "estimate scatters along the path more than a located camera. Six worlds x 3 "
        "conditions, 3 starts: summed 14.04 -> 13.77 m, no cell worse")
    along_track_alpha_weak: float = Field(
        0.15, gt=0, le=1, description="... and for such a frame that is also weak (best "
        "match below coast_ratio of the tracking level): the smoother's prediction carries "
        "the position (with steering, 11.94 -> 11.75 m)")
    along_track_gate_m: float = Field(
        10.0, gt=0, le=1e5, description="a correction longer than this (m) restarts the "
        "smoother at the swarm's estimate")
    metric_pose: bool = Field(
        True, description="while tracking, locate the camera between map images by two-view "
        "geometry against the best-matching map image near the estimate (service/"
        "metric_pose.py; needs a map built with the camera's intrinsics): the robot's offset "
        "beside and along the recorded path, which images alone cannot tell")
    metric_gate_m: float = Field(
        3.0, gt=0, le=1e3, description="a frame located within this (m) of the held place's "
        "map image confirms the place (the verify rules below)")
    metric_reach_m: float = Field(
        15.0, gt=0, le=1e3, description="a located position farther than this (m) from its "
        "map image is not taken. The geometry corrects the place the swarm holds: six worlds "
        "x 3 conditions (3 starts, with kidnap) summed 41.9 m with 3 m, 39.3 m with 15 m, no "
        "cell worse (sums added by hand from the printed per-run sums); a located camera 6-8 m "
        "from its image is 1.6 m off (median), the image 7.0 m")
    metric_steer_m: float = Field(
        1.0, ge=0, le=1e3, description="a frame located farther than this (m) from the "
        "swarm's estimate steers the swarm: the best sub-swarm is attracted to the located "
        "position and its quantum particles and local scouts are drawn around it (the swarm "
        "otherwise keeps a place the geometry corrects frame after frame). Six worlds x 3 "
        "conditions, 3 starts: summed 14.04 -> 12.17 m (3 m: 13.02 m); it loses seed 23's "
        "sunny map / cloudy round, 1.03 -> 1.12 m, in a stretch no image near the truth "
        "matches. 0 switches it off")
    metric_tries: int = Field(
        4, ge=1, le=64, description="images a frame is located against at most: the "
        "best-matching one near the estimate, then the next best compared within "
        "metric_search_m (only while none located it)")
    metric_search_m: float = Field(
        8.0, gt=0, le=1e3, description="radius (m) around the estimate of the further "
        "images tried")
    metric_map_sigma_m: float = Field(
        0.28, ge=0, le=1e3, description="std (m) of the map's recorded positions in each "
        "axis, which no frame can see: the floor of a located frame's radius "
        "(service/estimators/located_noise.py)")
    metric_jitter_gain: float = Field(
        1.65, ge=0, le=1e3, description="a located frame's radius per axis is "
        "sqrt(metric_map_sigma_m^2 + (gain * jitter)^2), jitter the located positions' "
        "frame-to-frame noise measured in the session. 0.28 and 1.65 put the median of six "
        "worlds x 3 conditions at 70 % of tracked frames within accuracy_m, the middle of "
        "60-80 %; centred on three worlds, each half puts 8-9 of the other three's nine "
        "cells in 60-80 %")
    metric_jitter_prior_m: float = Field(
        0.15, ge=0, le=1e3, description="the jitter (m) assumed until eight located triples "
        "of consecutive frames were seen")
    verify_frames: int = Field(
        0, ge=0, le=10_000, description="while tracking, a frame the geometry could not "
        "locate at the best image near the estimate for this many tracked frames in a row "
        "is not good for the lost detection (at the true place 80-100 % of tracked frames "
        "are located, more than 5 m off 0-4 %). 0, the default, switches it off: with 6, "
        "frames more than 10 m off were reported lost or recovering 25-71 % instead of "
        "0-56 % of the time, but the mean error over six worlds x 3 conditions summed "
        "17.93 m against 17.56 m (recoveries where the place was right)")
    verify_switch_frames: int = Field(
        0, ge=0, le=10_000, description="after this many tracked frames in a row that could "
        "not be located at the held place, the estimate moves to another sub-swarm (of the "
        "next two) where the frame is located. 0, the default, switches it off: with 3, six "
        "worlds x 3 conditions summed 16.03 m against 17.54 m (hard pairs 1.55 -> 1.14 m on "
        "seed 0, 2.25 -> 1.70 m on seed 11) but lost on two (seed 23 cloudy 1.21 -> 1.24 m, "
        "seed 58 hard pair 1.14 -> 1.24 m)")
    @model_validator(mode="after")
    def _consistent(self) -> Self:
        _check(self.v0_min <= self.v0 <= self.v0_max, "need v0_min <= v0 <= v0_max")
        _check(self.min_axis_range_m <= self.max_axis_range_m,
               "need min_axis_range_m <= max_axis_range_m")
        _check(self.adapt_low < self.adapt_high, "need adapt_low < adapt_high")
        return self


class PFParams(CommonParams):
    """Particle filter baselines (Sec. 7.2): PF-g (Gaussian motion) and PF-l (Eqs. 7-8)."""

    n_particles: int = Field(300, ge=1, le=MAX_PARTICLES,
                             description="particles; cost per frame grows with it")
    sigma_gauss_m: float = Field(4.0, ge=0, le=1e4, description="PF-g motion noise per "
                                 "iteration (m)")
    sigma_rot_deg: float = Field(60.0, ge=0, le=360, description="PF-l rotation noise per "
                                 "iteration (degrees)")
    sigma_acc: float = Field(1e-3, ge=0, le=10, description="PF-l log-speed noise per "
                             "iteration")
    v_init_mps: float = Field(2.0, ge=0, le=100, description="PF-l initial speed |v(0)| "
                              "(m/s), about 3 v_R in the paper")
