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
        2.0, gt=0, le=1000, description="zeta of Eq. 3 (m): a particle's fitness is scaled "
        "by a Gaussian of its distance to its nearest map image; the papers give no value, "
        "and 2 m keeps full credit within a street's lateral spread and halves it ~2.4 m off "
        "the recorded path")
    lost_threshold: float = Field(
        0.05, ge=0, le=1, description="similarity m (share of matched features) below which "
        "a frame's best match counts as bad for the papers' DPSO and the particle filters; "
        "0.05 is the papers' 'matching less than 5 % of local features' (Sec. 5)")
    lost_frames: int = Field(
        3, ge=1, le=1000, description="bad frames in a row before the robot is reported "
        "lost (frames); 3 is the papers' 'several iterations in a row' (Sec. 5): it ignores "
        "one blurred frame and reacts within ~2 m at 0.6 m per frame")
    converge_frames: int = Field(
        3, ge=1, le=1000, description="good frames in a row before 'initializing' becomes "
        "'tracking' (frames); 3, symmetric with lost_frames")
    default_dt_s: float = Field(
        1.0, gt=0, le=3600, description="frame interval assumed when frames carry no "
        "timestamps (s); 1 s is the papers' one image per second")
    ema_alpha: float = Field(
        0.125, gt=0, le=1, description="weight of the exponential moving average of the "
        "tracked velocity and the frame interval, which DPSO's self-adaptation also reads "
        "(no unit); 1/8 is the journal's footnote 1")
    init_spread_m: float = Field(
        2.0, ge=0, le=1000, description="spread of the global start's particles around "
        "randomly drawn map images (m); 2 m because localization is only possible near map "
        "images, and a uniform placement would waste most particles off the route")
    odom_var_xy: float = Field(
        0.0025, ge=0, le=100, description="variance of a wheel-odometry step's position per "
        "metre travelled (m^2/m) where the robot sends none; 0.0025 is a 5 cm std per "
        "metre, above the lab's simulated 3 % scale error "
        "(service/estimators/odometry.py)")
    odom_var_yaw: float = Field(
        0.0003, ge=0, le=100, description="variance of the odometry's heading per metre "
        "travelled (rad^2/m) where the robot sends none: how fast the odometry's heading "
        "drifts from the map's between fits; 0.0003 is 1 degree std per metre")


class DPSOParams(CommonParams):
    """Dynamic PSO, Eqs. 4-6 and the self-adaptation of Sec. 5, plus the multi-swarm
    extensions of service/estimators/multi_swarm_dpso.py. The measurements behind the
    defaults: docs/research/lighting.md and docs/research/papers.md."""

    n_particles: int = Field(80, ge=2, le=MAX_PARTICLES,
                             description="swarm size (particles); 80 as in the papers' "
                             "DPSO-80 (Sec. 7.1), and the cost per frame grows with it")
    omega: float = Field(0.99, ge=0, le=2, description="inertia of Eq. 4 (no unit); the "
                         "papers' 0.99")
    phi0: float = Field(0.3, ge=0, le=10, description="weight of the random perturbation "
                        "in Eq. 4 (no unit); the papers' 0.3")
    phi2: float = Field(0.6, ge=0, le=10, description="weight of the attraction to the "
                        "neighbourhood best p^n in Eq. 4, star topology (no unit); the "
                        "papers' 0.6")
    v0: float = Field(0.015, gt=0, le=1, description="maximum velocity (fraction of the "
                      "axis range per iteration) and the start value of the "
                      "self-adaptation; 0.015 is the conference paper's setting for the "
                      "original speed")
    v0_spacings: float = Field(
        2.0, ge=0, le=1000, description="multi-swarm DPSO: v0 starts at least this many map "
        "image spacings per frame (over the longer axis range, at most v0_max), so that on a "
        "short map with images far apart the swarm can follow a robot that moves one image "
        "per frame (the self-adaptation's target is twice the swarm's speed); 2 leaves "
        "routes of ~100 m with images ~0.6 m apart at v0; 0: v0 as given")
    v0_min: float = Field(0.001, gt=0, le=1, description="floor of v0's self-adaptation "
                          "(fraction of the axis range per iteration); our choice, so the "
                          "swarm never freezes")
    v0_max: float = Field(0.1, gt=0, le=1, description="ceiling of v0 in recovery "
                          "(fraction of the axis range per iteration); 0.1 crosses the "
                          "search space in about 10 iterations, as the papers ask")
    quantum_ratio: float = Field(0.1, ge=0, le=1, description="q_r, the share of quantum "
                                 "particles of Eq. 6 (no unit); the papers' 10 %")
    quantum_ratio_max: float = Field(0.2, ge=0, le=1, description="ceiling of q_r in "
                                     "recovery (no unit); the papers' 20 %")
    quantum_sigma: float = Field(0.15, ge=0, le=10, description="q_d, the standard "
                                 "deviation of the quantum particles (fraction of the axis "
                                 "range); the papers' 0.15")
    high_energy_ratio: float = Field(0.1, ge=0, le=1, description="h_r, the share of "
                                     "particles allowed high_energy_factor * v0 (no unit); "
                                     "the papers' 10 %")
    high_energy_factor: float = Field(3.0, ge=0, le=100, description="speed factor of the "
                                      "high-energy particles (times v0); the papers' 3")
    phi2_min: float = Field(0.01, ge=0, le=10, description="floor of phi2 in recovery (no "
                            "unit); the papers' 0.01, so the swarm spreads out")
    adapt_low: float = Field(0.4, gt=0, le=10, description="lower end of the band in which "
                             "the self-adaptation keeps EMA(swarm speed) / v0 (no unit); the "
                             "papers' 0.4")
    adapt_high: float = Field(0.6, gt=0, le=10, description="upper end of that band (no "
                              "unit); the papers' 0.6")
    adapt_step: float = Field(0.1, ge=0, le=1, description="relative change of v0 per "
                              "iteration while the ratio is outside the band (no unit); the "
                              "papers' 10 %")
    recovery_step: float = Field(
        0.35, ge=0, le=1, description="relative step per frame by which recovery raises v0 "
        "and q_r and lowers phi2 towards their limits (no unit); Sec. 5 gives no rate, and "
        "0.35 recovered from a kidnapping fastest in `swarmloc sweep`")
    recovered_frames: int = Field(
        3, ge=1, le=1000, description="good frames in a row that end the recovery phase "
        "(frames); 3, symmetric with lost_frames, beat 1 in `swarmloc sweep`: one spurious "
        "match no longer ends the search")
    min_axis_range_m: float = Field(
        20.0, gt=0, le=1e6, description="smallest axis range delta_i (m); 20 m so that a "
        "straight route still has lateral exploration")
    place_candidates: int = Field(
        10, ge=0, le=1000, description="while searching (global start, lost, recovering), "
        "random placements go around this many top images of the map's place index for the "
        "frame instead of random map images (images; 0 or a map without an index: random "
        "map images); 10 finds a kidnapped robot on a 40,000-image map within a few frames")
    max_axis_range_m: float = Field(
        200.0, gt=0, le=1e7, description="largest axis range delta_i (m); 200 m keeps the "
        "swarm's velocities and spread street-sized on maps of any extent (long jumps come "
        "from the place index) and leaves the papers' routes unchanged")
    variant: DPSOVariant = Field(
        "swarmloc", description="'swarmloc': the multi-swarm DPSO with path evidence, scouts "
        "and relative lost detection (the default, built for changing light); 'paper': the "
        "journal's DPSO as published")
    motion_prior: bool = Field(
        False, description="carry the particles by the tracked velocity while tracking; off "
        "because together with the inertia omega it overshoots")
    predict_attractor: bool = Field(
        False, description="attract each sub-swarm to where its seed will be at the next "
        "frame (seed + tracked step), for robots that move about an image spacing per frame; "
        "off by default because it does not win in every condition")
    evidence_decay: float = Field(0.8, ge=0, lt=1, description="lambda of the path "
                                  "evidence A <- lambda A + fitness (no unit); 0.8 is about "
                                  "five frames of memory")
    species_radius_m: float = Field(5.0, gt=0, le=1e4, description="particles within this "
                                    "distance of a seed form its sub-swarm (m); 5 m, our "
                                    "choice: about eight image spacings of 0.6 m")
    max_species: int = Field(4, ge=1, le=64, description="most sub-swarms (competing "
                             "places) held at once; 4, our choice: each keeps about 20 of "
                             "the 80 particles")
    dissolve_ratio: float = Field(0.5, ge=0, le=1, description="a sub-swarm whose support "
                                  "falls below this share of the best one's dissolves into "
                                  "it (no unit); 0.5 measured better than 0.25")
    dissolve_mean_ratio: float = Field(
        1.0, ge=0, le=100, description="... unless the mean evidence along its particles' "
        "paths is at least this share of the best one's (no unit; 0: the support alone); 1 "
        "lets a young sub-swarm that is better per frame survive its first frames")
    hypothesis_ratio: float = Field(0.1, ge=0, le=1, description="sub-swarms are reported "
                                    "as hypotheses down to this share of the best one's "
                                    "support (no unit)")
    scout_ratio: float = Field(0.03, ge=0, le=1, description="share of the particles with "
                               "the least evidence redrawn at random map images every frame "
                               "(no unit); 3 % gives the lost detection its background and "
                               "finds a kidnapped robot")
    scout_ratio_recovery: float = Field(0.1, ge=0, le=1, description="... the same share "
                                        "while recovering (no unit): 10 % searches faster")
    scout_unconfirmed: bool = Field(
        True, description="on a map with the camera, the scouts are drawn at "
        "scout_ratio_recovery also while tracking is not yet confirmed (confirm_tracking: "
        "the swarm converged or came back, and no frame was located at the held place "
        "since): a swarm that settled on a look-alike before its first fix searches as "
        "if recovering")
    quantum_track_sigma_m: float = Field(2.0, ge=0, le=1e4, description="spread of Eq. 6's "
                                         "quantum particles while tracking (m; the papers' "
                                         "q_d otherwise); 2 m stays near the held place")
    distinct_ratio: float = Field(3.0, ge=0, le=1e3, description="a frame is good when its "
                                  "best match near the estimate is at least this many times "
                                  "the background of far images (no unit); 3 tells a change "
                                  "of light (all matches weak) from a wrong place")
    distinct_floor_m: float = Field(0.004, ge=0, le=1, description="... and at least this "
                                    "similarity m (share of features; 4 in 1,000), so noise "
                                    "alone never counts as good")
    vouch_distinct: float = Field(2.0, ge=0, le=1e3, description="on a map of two feature "
                                  "types, a frame whose fused m is not good counts as good "
                                  "while tracking when the first type's own m is good and "
                                  "the fused m stands out at least this many times (no unit; "
                                  "0: never): RootSIFT vouches for a place XFeat's chance "
                                  "level hides")
    distinct_far_m: float = Field(10.0, ge=0, le=1e5, description="images farther than this "
                                  "from the best form that background (m); 10 m, our choice: "
                                  "beyond the true place's neighbours, which look like it")
    estimate_radius_m: float = Field(2.5, gt=0, le=1e4, description="the particles' estimate "
                                     "averages the best sub-swarm within this distance of "
                                     "its best particle (m); 2.5 m, about four image spacings")
    estimate_floor_m: float = Field(0.5, ge=0, le=1e4, description="standard deviation added "
                                    "to the sub-swarm's spread in the estimate's covariance "
                                    "(m); 0.5 m, so a tight swarm is not reported as exact")
    covariance_scale: float = Field(
        0.1, gt=0, le=100, description="scale of the best sub-swarm's covariance in the "
        "estimate's covariance (no unit); 0.1, calibrated with match_sigma_m and "
        "lateral_sigma_m so that about 68 % of tracked frames fall within accuracy_m")
    match_sigma_m: float = Field(
        0.375, ge=0, le=1e3, description="standard deviation added for the match strength, "
        "match_sigma_m * m_best ** -match_sigma_power (m; 0.75 m at m = 0.06); weak matches "
        "place the robot less sharply, and 0.375 m is the calibrated value")
    lateral_sigma_m: float = Field(
        0.6, ge=0, le=1e3, description="standard deviation added for the robot's offset from "
        "the recorded path, which images along one path cannot tell (m); 0.6 m, calibrated on "
        "test worlds whose rounds drive 0-1.2 m beside the map's path")
    match_sigma_power: float = Field(
        0.25, ge=0, le=4, description="exponent of match_sigma_m's dependence on m_best (no "
        "unit); 0.25, calibrated with it")
    estimate_image_radius_m: float = Field(
        4.0, ge=0, le=1e4, description="the estimate is the centre of the map images compared "
        "within this distance of the best sub-swarm, weighted by m ** estimate_image_power "
        "(m; 0: the particles' centre); 4 m holds the neighbours the images interpolate "
        "between, and the particles themselves lag the robot")
    estimate_image_power: float = Field(
        8.0, ge=0, le=64, description="exponent of the similarity weights of that centre (no "
        "unit); 8 lets the best images dominate")
    coast_ratio: float = Field(
        0.65, ge=0, le=1, description="a frame whose best match is below this share of the "
        "level seen while tracking is weak, and through weak frames the tracked velocity "
        "carries the swarm (no unit; 0: no coasting); 0.65 beat 0.35, 0.5 and 0.8")
    coast_max_frames: int = Field(
        30, ge=0, le=100_000, description="most weak frames in a row coasted through "
        "(frames); 30, after which a lasting drop becomes the new level")
    level_alpha: float = Field(
        0.1, ge=0, le=1, description="weight of the moving average of the best match while "
        "tracking, the level coast_ratio compares with (no unit); 0.1, about ten frames")
    local_scout_ratio: float = Field(
        0.1, ge=0, le=1, description="share of the particles redrawn at map images between "
        "local_scout_inner_m and local_scout_radius_m of the estimate every "
        "local_scout_every-th frame while tracking (no unit; 0: none); 10 % gives the swarm "
        "the local search of a particle filter's motion noise, so a swarm stalled where the "
        "robot stopped finds it again")
    local_scout_radius_m: float = Field(
        15.0, ge=0, le=1e5, description="outer radius of the local scouts (m); 15 m reaches "
        "a robot that moved on during a stall")
    local_scout_inner_m: float = Field(
        4.0, ge=0, le=1e5, description="inner radius of the local scouts (m); 4 m, because "
        "the swarm and the estimate already compare the nearer images")
    local_scout_every: int = Field(
        2, ge=1, le=1000, description="local scouts every this many frames (frames); every "
        "2nd frame halves their comparisons, and a stall grows over tens of frames")
    local_scout_unlocated: bool = Field(
        True, description="on a map with the camera, no local scouts on a frame the "
        "geometry located at the held place (at its best image near the estimate, within "
        "metric_gate_m; with odometry, a located position the odometry does not contradict): "
        "the swarm is where the robot is, and the scouts' comparisons would only cost")
    along_track_alpha: float = Field(
        0.7, gt=0, le=1, description="share of the along-path correction the reported "
        "position takes each tracked frame, all of it across the path "
        "(service/estimators/along_track.py; no unit; 1: no smoothing); 0.7 damps the "
        "scatter of neighbouring images that look alike without lagging at turns")
    along_track_alpha_unlocated: float = Field(
        0.35, gt=0, le=1, description="along_track_alpha for a tracked frame the geometry "
        "ran on but could not locate (no unit); 0.35, because such an image estimate "
        "scatters along the path more than a located camera")
    along_track_alpha_weak: float = Field(
        0.15, gt=0, le=1, description="... and for such a frame that is also weak (no unit); "
        "0.15 lets the smoother's prediction carry the position")
    along_track_gate_m: float = Field(
        10.0, gt=0, le=1e5, description="a correction longer than this restarts the "
        "smoother at the swarm's estimate, and DPSO's estimate moving this much farther "
        "than the predicted step is a jump that does not teach the tracked velocity (m); "
        "10 m, so a real jump is reported at once")
    odom_look: bool = Field(
        True, description="with wheel odometry, a located frame's camera yaw also corrects "
        "the odometry's map heading (service/estimators/odometry.py)")
    odom_drift: bool = Field(
        True, description="with wheel odometry and odom_look, the located frames' camera "
        "yaw also estimates the odometry's heading drift per metre travelled, and each "
        "odometry step's turn is corrected by it before it moves the swarm "
        "(service/estimators/odom_drift.py)")
    odom_alpha: float = Field(
        0.3, ge=0, le=1, description="with wheel odometry, the share of the image "
        "estimate's correction (along and across the path) the reported position takes "
        "while tracking; the odometry's prediction carries the rest (an alpha filter whose "
        "prediction is the odometry step; a correction beyond along_track_gate_m restarts "
        "it at the estimate) (no unit)")
    odom_alpha_weak: float = Field(
        0.0, ge=0, le=1, description="with wheel odometry, the share of the correction "
        "(along and across the path) the reported position takes from a frame the images "
        "do not confirm (not located where the map's geometry runs; weak without it); the "
        "odometry's prediction carries the rest, and such a frame farther than "
        "along_track_gate_m from it is not taken at all; 0, because such an image "
        "estimate lags the robot where the map's images look alike (no unit)")
    odom_carry_frames: int = Field(
        8, ge=0, le=100000, description="with wheel odometry, frames the reported position "
        "is carried by the odometry alone while the swarm has lost the place and searches "
        "(the lost detection fires where no match stands out, e.g. a stretch the map does "
        "not show); the search's own estimate is reported after that, or at once where it "
        "lies beyond along_track_gate_m and a match stands out there (a kidnap); back to "
        "tracking, the images correct the carried position as usual; 0: the search's "
        "estimate at once (frames)")
    odom_restart_heading: bool = Field(
        True, description="with wheel odometry, a jump of the estimate beyond "
        "along_track_gate_m from the odometry's track (a kidnap) also restarts the "
        "odometry's map heading (the direction of motion until a new fit; "
        "service/estimators/odometry.py)")
    odom_locate_gate_m: float = Field(
        1.5, ge=0, le=1e5, description="with wheel odometry, a located frame farther than "
        "this from the odometry's prediction of the reported position is held back until "
        "the next located frame agrees with it within half this distance "
        "(service/estimators/odometry.py LocatedGate); 0: off (m)")
    metric_pose: bool = Field(
        True, description="while tracking, locate the camera between map images by two-view "
        "geometry against the best-matching map image near the estimate "
        "(service/vision/metric_pose.py; needs a map built with the camera's intrinsics); "
        "on, because images alone cannot tell the robot's offset beside and along the path")
    metric_second: bool = Field(
        True, description="on a map of two feature types, a frame RootSIFT's two-view "
        "geometry cannot locate is located with XFeat's matches: at dusk RootSIFT finds few "
        "matches (docs/research/lighting.md: dusk error 0 to -26 % on six worlds)")
    metric_gate_m: float = Field(
        3.0, gt=0, le=1e3, description="a frame located within this distance of the held "
        "place's map image confirms the place for the verify rules (m); 3 m separates the "
        "true place (most tracked frames located) from one more than 5 m off (almost none)")
    metric_reach_m: float = Field(
        15.0, gt=0, le=1e3, description="a located position farther than this from its map "
        "image is not taken (m); 15 m lets the geometry correct a place the swarm holds a "
        "few metres off, and beyond it located cameras are too often wrong")
    metric_steer_m: float = Field(
        1.0, ge=0, le=1e3, description="a frame located farther than this from the swarm's "
        "estimate steers the best sub-swarm, its quantum particles and local scouts to the "
        "located position (m; 0: no steering); 1 m, so the swarm follows the camera instead "
        "of being corrected frame after frame")
    metric_tries: int = Field(
        4, ge=1, le=64, description="most map images a frame is located against: the "
        "best-matching one near the estimate, then the next best within metric_search_m "
        "while none located it (images); 4 recovers a share of the frames the light leaves "
        "unlocatable at the first image")
    metric_search_m: float = Field(
        8.0, gt=0, le=1e3, description="radius around the estimate of the further images "
        "tried (m); 8 m, our choice: twice estimate_image_radius_m")
    metric_disagree_m: float = Field(
        8.0, ge=0, le=1e3, description="a tracked frame located farther than this from the "
        "images' estimate carries two answers that disagree: it is reported 'recovering', "
        "its accuracy_m at least that distance, while the swarm follows the located camera "
        "as usual (m; 0: off); 8 m, metric_search_m: at dusk such frames are single "
        "look-alikes 10-15 m off, in daylight almost never seen (docs/research/lighting.md)")
    jump_hold_m: float = Field(
        10.0, ge=0, le=1e4, description="a reported position farther than this from where "
        "the previous frame predicted it (the tracked step, or the odometry's) is a jump to "
        "another place: reported 'recovering', accuracy_m at least the jump, until "
        "jump_confirm_frames good frames in a row or one good located frame confirm it (m; "
        "0: off; report only); 10 m, two sub-swarm radii")
    jump_confirm_frames: int = Field(
        5, ge=1, le=1000, description="good frames in a row that confirm the place of a "
        "jump (frames); 5: at dusk a look-alike place the swarm jumps to can give three good "
        "frames in a row, more than a start's converge_frames (docs/research/lighting.md)")
    metric_map_sigma_m: float = Field(
        0.28, ge=0, le=1e3, description="standard deviation of the map's recorded positions "
        "per axis, the floor of a located frame's radius (m; "
        "service/estimators/located_noise.py); 0.28 m, calibrated with metric_jitter_gain "
        "for GPS-like map positions; a map whose positions were fused with odometry gives "
        "0.18 m unless the session sets it")
    metric_jitter_gain: float = Field(
        1.65, ge=0, le=1e3, description="a located frame's radius per axis is "
        "sqrt(metric_map_sigma_m^2 + (gain * jitter)^2), jitter being the located positions' "
        "frame-to-frame noise measured in the session (no unit); 1.65 puts the median of the "
        "test worlds at 70 % of tracked frames within accuracy_m")
    odom_jitter_share: float = Field(
        0.8, ge=0, le=1, description="with wheel odometry, while tracking, the share of the "
        "located positions' jitter left in the reported position (the odometry predicts and a "
        "located frame corrects odom_alpha of the difference, which averages part of it out): "
        "a located frame's radius is sqrt(metric_map_sigma_m^2 + (gain * share * jitter)^2); "
        "0.8, calibrated on three rendered worlds and checked on three others "
        "(docs/research/lighting.md); 1: as without odometry")
    metric_jitter_prior_m: float = Field(
        0.15, ge=0, le=1e3, description="the jitter assumed until eight located triples of "
        "consecutive frames were seen (m); 0.15 m, our choice for a session's first frames")
    confirm_tracking: bool = Field(
        True, description="where the map has the camera, a swarm that converged (or came back) "
        "reports 'tracking' only from the first frame located at the held place on (within "
        "metric_gate_m of its map image); until then 'recovering' (the report alone moves no "
        "estimate; scout_unconfirmed searches meanwhile). At the true place most tracked "
        "frames are located, more than 5 m off almost none: a look-alike place the swarm "
        "settles on at dusk is no longer reported as tracked")
    verify_frames: int = Field(
        0, ge=0, le=10_000, description="while tracking, a frame that could not be located "
        "at the held place for this many tracked frames in a row is not good for the lost "
        "detection (frames; 0: off); off by default because it reports a wrong place sooner "
        "but raises the mean error")
    verify_switch_frames: int = Field(
        0, ge=0, le=10_000, description="after this many tracked frames in a row not located "
        "at the held place, the estimate moves to another sub-swarm where the frame is "
        "located (frames; 0: off); off by default because it does not win in every condition")

    sequence_frames: int = Field(
        8, ge=0, le=10_000, description="the swarmloc variant: while the swarm searches for "
        "the first time (a new or reset session) and frames carry odometry, places along the "
        "map's path are followed by the wheels and scored frame after frame (sequence matching, "
        "service/estimators/place_sequence.py); one that has seen this many frames and stands "
        "out draws the swarm to it (frames; 0: off). 8: at dusk the start found the robot "
        "sooner on three of nine rendered worlds and changed nothing on the others "
        "(docs/research/lighting.md)")
    sequence_ratio: float = Field(
        1.3, ge=1, le=100, description="a followed place stands out when its mean score is "
        "at least this many times that of every other place 15 m or more away (no unit)")
    sequence_travel_m: float = Field(
        5.0, ge=0, le=1e4, description="... and the wheels moved it at least this far (m): a "
        "robot standing still repeats one frame, which makes no sequence")

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
                             description="particles; 300 as in the papers' PF-g-300 and "
                             "PF-l-300, and the cost per frame grows with it")
    sigma_gauss_m: float = Field(4.0, ge=0, le=1e4, description="PF-g motion noise per "
                                 "iteration (m); the papers' 4 m")
    sigma_rot_deg: float = Field(60.0, ge=0, le=360, description="PF-l rotation noise per "
                                 "iteration (degrees); 60, the papers' PF-l setting "
                                 "(Sec. 7.2)")
    sigma_acc: float = Field(1e-3, ge=0, le=10, description="PF-l log-speed noise per "
                             "iteration (no unit); 1e-3, the papers' PF-l setting")
    v_init_mps: float = Field(2.0, ge=0, le=100, description="PF-l initial speed |v(0)| "
                              "(m/s); 2 m/s, about 3 v_R in the papers")
