"""Pydantic schemas shared by the HTTP and Zenoh transports (the single source of the API)."""

from __future__ import annotations

import math
import re
from typing import Any, Literal, Self, TypeVar, get_args

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from pydantic.json_schema import JsonDict

from service.api.errors import InvalidParameters, describe_errors
from service.api.params import DPSOParams, PFParams

# the largest radius a prior may have (m): beyond it a prior says nothing
MAX_PRIOR_RADIUS_M = 10_000.0
# |x|, |y| of any pose at most (m); the service also checks the map's extent plus a margin
COORD_LIMIT_M = 1e7

#: the one robot-id rule of every transport (HTTP paths, Zenoh keys, ROS 2 namespaces):
#: 1-128 ASCII letters, digits, '-', '_' or '.', and not dots only ('.', '..' are paths)
ROBOT_ID_MAX_LENGTH = 128
ROBOT_ID_PATTERN = r"^[A-Za-z0-9._-]*[A-Za-z0-9_-][A-Za-z0-9._-]*$"
_ROBOT_ID = re.compile(ROBOT_ID_PATTERN, re.ASCII)
#: a frame's timestamp t (s): |t| below this, and at most MAX_T_STEP_S after the robot's
#: previous frame (a stamp of 1e300 or 2^31-1 s would otherwise lock the robot out)
MAX_ABS_T_S = 1e10
MAX_T_STEP_S = 86_400.0

M = TypeVar("M", bound=BaseModel)
StatusName = Literal["initializing", "tracking", "recovering", "lost"]
#: every estimator's name, listed once (``service.estimators.registry`` dispatches each to its
#: class)
EstimatorName = Literal["dpso", "pf-g", "pf-l"]
#: how a frame's RootSIFT features are compared with a map image's (service/maps/route_map.py):
#: "exact" every pair, "words" only the pairs that share a visual word (inverted file),
#: "auto" words on a map whose images hold more features than a frame keeps by default
Matcher = Literal["auto", "exact", "words"]
MATCHERS: tuple[str, ...] = get_args(Matcher)
#: what an Estimate's heading is (service/estimators/odometry.py)
HeadingSource = Literal["motion", "odometry", "camera"]
#: search radius of a pose prior or a reset near a pose when the robot gives none, m
DEFAULT_PRIOR_RADIUS_M = 5.0


class Hypothesis(BaseModel):
    """A competing position hypothesis (a DPSO sub-swarm)."""

    x: float = Field(description="m east")
    y: float = Field(description="m north")
    weight: float = Field(description="share of the support of all hypotheses, 0-1")


class Estimate(BaseModel):
    """One localization result: what a ROS 2 bridge needs for PoseWithCovarianceStamped."""

    model_config = ConfigDict(frozen=True)

    seq: int = Field(description="frame counter of the session, from 1")
    stamp: float | None = Field(description="frame timestamp (s) as sent by the robot")
    frame_id: str = Field(description="map name: the local east/north frame of the estimate")
    estimator: EstimatorName
    x: float = Field(description="metres east in the map frame")
    y: float = Field(description="metres north in the map frame")
    lat: float | None = Field(None, description="WGS84 latitude when the map has an origin")
    lon: float | None = Field(None, description="WGS84 longitude when the map has an origin")
    heading: float = Field(description="the robot's heading, rad counter-clockwise from "
                           "east; heading_source says what it is")
    heading_source: HeadingSource = Field(
        "motion", description="'odometry': the robot's wheel-odometry yaw turned into the map "
        "(its variance in pose_covariance's yaw entry); 'camera': the camera's yaw located by "
        "two-view geometry (likewise); 'motion': the direction of motion, whose yaw variance "
        "is given as unknown (1e6)")
    speed: float = Field(description="speed estimate, m/s")
    status: StatusName
    lost: bool = Field(description="best match below the lost threshold for several frames")
    score: float = Field(description="best image similarity m of this frame, 0..1")
    comparisons: int = Field(description="distinct map images compared for this frame")
    covariance: list[list[float]] = Field(description="2x2 position covariance, m^2")
    pose_covariance: list[float] = Field(
        description="6x6 row-major covariance (x, y, z, roll, pitch, yaw) for ROS; "
        "unknown entries carry 1e6")
    accuracy_m: float = Field(description="radius of the 68 % horizontal confidence disc, m")
    nearest_image: int = Field(description="id of the map image nearest to the estimate")
    nearest_image_name: str
    spread_m: float = Field(description="mean distance of the particles to their centre, m")
    hypotheses: list[Hypothesis] = Field(
        default_factory=list,
        description="competing places the swarm holds (best first; the estimate follows the "
                    "first); more than one means the place is ambiguous")
    robot_id: str | None = None
    input_seq: int | None = Field(None, description="sequence number sent with the frame")
    experience: str | None = Field(
        None, description="the experience (a map layer the fleet learned) this frame was "
        "matched with; null: the map's own images")


class ErrorBody(BaseModel):
    error: str
    detail: Any | None = None




class PosePrior(BaseModel):
    """A known position with an uncertainty radius (like AMCL's initial pose). Finite, and
    within the map's extent plus ``SWARMLOC_POSE_MARGIN_M`` (checked against the map)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)

    x: float = Field(description="metres east in the map frame", ge=-COORD_LIMIT_M,
                     le=COORD_LIMIT_M)
    y: float = Field(description="metres north in the map frame", ge=-COORD_LIMIT_M,
                     le=COORD_LIMIT_M)
    radius: float = Field(DEFAULT_PRIOR_RADIUS_M, description="search radius, m", gt=0,
                                 le=MAX_PRIOR_RADIUS_M)


def check_robot_id(robot_id: str) -> str:
    """``robot_id`` if it follows the robot-id rule, else InvalidParameters (422)."""
    if len(robot_id) > ROBOT_ID_MAX_LENGTH or not _ROBOT_ID.fullmatch(robot_id):
        raise InvalidParameters(
            f"robot id {robot_id[:40]!r}{'...' if len(robot_id) > 40 else ''} must be 1-"
            f"{ROBOT_ID_MAX_LENGTH} ASCII letters, digits, '-', '_' or '.', not dots only")
    return robot_id


def check_timestamp(t: float, last_t: float | None) -> None:
    """A frame's t: finite, |t| < MAX_ABS_T_S, at most MAX_T_STEP_S after ``last_t``;
    else InvalidParameters (422)."""
    if not (math.isfinite(t) and abs(t) < MAX_ABS_T_S):
        raise InvalidParameters(f"timestamp t={t:g} must be a finite number of seconds below "
                                f"{MAX_ABS_T_S:g} in magnitude")
    if last_t is not None and t > last_t + MAX_T_STEP_S:
        raise InvalidParameters(f"timestamp t={t:g} is more than {MAX_T_STEP_S:g} s after the "
                                f"robot's previous frame ({last_t:g}); reset the session to "
                                "start a new clock")


def validated(model: type[M], data: Any, what: str) -> M:
    """``model`` from ``data`` or InvalidParameters (422) with one line per problem: the
    one validation of every transport, so HTTP and Zenoh give the same message."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise InvalidParameters(f"invalid {what}: {describe_errors(exc.errors())}") from None


def pose_prior(x: float | None, y: float | None, radius: float | None) -> PosePrior | None:
    """A prior from separate values (frame query, attachment): both x and y or neither."""
    if x is None and y is None:
        if radius is not None:
            raise InvalidParameters("a prior radius needs prior x and y")
        return None
    if x is None or y is None:
        raise InvalidParameters("a pose prior needs both x and y")
    data = {"x": x, "y": y} | ({"radius": radius} if radius is not None else {})
    return validated(PosePrior, data, "pose prior")


_PARAMS_SCHEMA: JsonDict = {"anyOf": [DPSOParams.model_json_schema(), PFParams.model_json_schema()]}


class SessionConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)

    map: str | None = Field(None, max_length=128,
                            description="map name; default: the service's default map")
    estimator: EstimatorName | None = Field(None, description="default: the service default")
    params: dict[str, Any] = Field(
        default_factory=dict, json_schema_extra=_PARAMS_SCHEMA,
        description="estimator parameter overrides: DPSOParams for dpso, PFParams for pf-g "
        "and pf-l (strict types, finite, bounded; n_particles also by SWARMLOC_MAX_PARTICLES)")
    seed: int = Field(0, ge=0, lt=2**63,
                      description="random seed: same seed and frames, same estimates")
    initial_pose: PosePrior | None = None
    learn: bool = Field(False, description="frames where this session is confidently "
                        "localized teach its map a new experience (a layer of today's light)")
    condition: str | None = Field(None, min_length=1, max_length=32,
                                  pattern=r"^[A-Za-z0-9_.-]+$",
                                  description="the light of this session's frames (e.g. "
                                  "'cloudy'): the tag of the experience it teaches")


class ResetRequest(BaseModel):
    """``POST /sessions/{id}/reset`` and Zenoh ``{"action": "reset"}``: no pose (global
    re-initialisation) or x and y (and optionally radius) near a pose."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)

    x: float | None = Field(None, description="metres east in the map frame",
                            ge=-COORD_LIMIT_M, le=COORD_LIMIT_M)
    y: float | None = Field(None, description="metres north in the map frame",
                            ge=-COORD_LIMIT_M, le=COORD_LIMIT_M)
    radius: float | None = Field(None, description=f"search radius, m (default "
                                 f"{DEFAULT_PRIOR_RADIUS_M})", gt=0,
                                 le=MAX_PRIOR_RADIUS_M)

    @model_validator(mode="after")
    def _both_or_neither(self) -> Self:
        if (self.x is None) != (self.y is None):
            raise ValueError("reset near a pose needs both x and y")
        if self.x is None and self.radius is not None:
            raise ValueError("a reset radius needs x and y")
        return self

    def near(self) -> PosePrior | None:
        if self.x is None or self.y is None:
            return None
        return PosePrior(x=self.x, y=self.y,
                         radius=self.radius if self.radius is not None else DEFAULT_PRIOR_RADIUS_M)


# the longest odometry step between two frames (m): a longer one is a glitch or a reset
# odometry, refused (reset the session, or send the frame without odometry, to restart it)
MAX_ODOM_STEP_M = 100.0
# |yaw| of an odometry pose at most (rad): a yaw that has wound this far is not a pose
ODOM_YAW_LIMIT_RAD = 1e4
# an odometry variance per metre travelled at most (m^2/m, rad^2/m)
ODOM_VAR_LIMIT = 100.0


class Odometry(BaseModel):
    """The robot's pose in its own odometry frame at the frame's time (nav2's
    ``odom->base_link``): the service uses the change between consecutive frames, so the
    frame's origin and drift do not matter. Variances are per metre travelled."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)

    x: float = Field(description="m, odometry frame", ge=-COORD_LIMIT_M, le=COORD_LIMIT_M)
    y: float = Field(description="m, odometry frame", ge=-COORD_LIMIT_M, le=COORD_LIMIT_M)
    yaw: float = Field(description="rad counter-clockwise, odometry frame",
                       ge=-ODOM_YAW_LIMIT_RAD, le=ODOM_YAW_LIMIT_RAD)
    var_xy: float | None = Field(None, ge=0, le=ODOM_VAR_LIMIT,
                                 description="position variance per metre travelled, m^2/m "
                                 "(default: the estimator's odom_var_xy)")
    var_yaw: float | None = Field(None, ge=0, le=ODOM_VAR_LIMIT,
                                  description="heading variance per metre travelled, "
                                  "rad^2/m (default: the estimator's odom_var_yaw)")


def odometry(x: float | None, y: float | None, yaw: float | None,
             var_xy: float | None = None, var_yaw: float | None = None) -> Odometry | None:
    """Odometry from separate values (frame query): x, y and yaw all or none."""
    given = [v is not None for v in (x, y, yaw)]
    if not any(given):
        if var_xy is not None or var_yaw is not None:
            raise InvalidParameters("odometry variances need odom_x, odom_y and odom_yaw")
        return None
    if not all(given):
        missing = [n for n, g in zip(("odom_x", "odom_y", "odom_yaw"), given, strict=True)
                   if not g]
        raise InvalidParameters(f"odometry needs odom_x, odom_y and odom_yaw together; "
                                f"missing {', '.join(missing)}")
    data = {"x": x, "y": y, "yaw": yaw} | ({"var_xy": var_xy} if var_xy is not None else {}) \
        | ({"var_yaw": var_yaw} if var_yaw is not None else {})
    return validated(Odometry, data, "odometry")


class FrameMeta(BaseModel):
    """A Zenoh frame's attachment ``{"t", "seq", "prior"}``: the HTTP frame query."""

    model_config = ConfigDict(allow_inf_nan=False, strict=True)

    t: float | None = Field(None, description="frame timestamp, s")
    seq: int | None = Field(None, ge=-(2**63), lt=2**63,
                            description="robot's frame sequence number")
    prior: PosePrior | None = None
    odom: Odometry | None = None


class LearningInfo(BaseModel):
    """What a learning session has taught so far (docs/operations/experiences.md): each
    frame is taught, bridged by the wheels, or stopped by one gate."""

    experience: str = Field(description="id of the experience its images join")
    frames: int = Field(description="frames the gates have judged")
    taught: int = Field(description="frames that passed every gate")
    bridged: int = Field(description="frames the wheels placed: between two taught ones, "
                         "or before the session's first taught frame (its start)")
    collected: int = Field(description="images collected and not yet handed to the map "
                           "writer (written every learn_commit_images, at a reset and when "
                           "the session ends)")
    stopped: dict[str, int] = Field(
        description="frames stopped, by gate: confident (not tracking), path (off the "
        "recent path), appearance (the map already matches it well, or has no image near), "
        "located (the two-view geometry does not place it near the estimate), place (an "
        "image of this experience is already there)")


class SessionInfo(BaseModel):
    robot_id: str
    map: str
    estimator: EstimatorName
    seed: int
    params: dict[str, Any]
    frames: int
    created: float
    last_used: float
    last_estimate: Estimate | None = None
    map_checksum: str | None = Field(
        None, description="version of the map the session runs on: a version that only "
        "adds or removes experiences is taken up live at the next frame (not by a learning "
        "session); a replaced map keeps serving its sessions until they are reset")
    learn: bool = Field(False, description="the session teaches its map (experiences)")
    condition: str | None = None
    learning: LearningInfo | None = Field(
        None, description="a learning session's progress on the replica that answers (each "
        "replica collects the frames it served); null for a session that does not learn, or "
        "one that has sent this replica no frame yet")


class ExperienceInfo(BaseModel):
    """One experience of a map: a layer the fleet learned (service/maps/experiences.py)."""

    id: str
    layer: int = Field(description="the map layer of its images")
    created: str = Field(description="when it was first written (ISO 8601, UTC)")
    updated: str | None = Field(None, description="when images were last added")
    condition: str | None = Field(None, description="the light, as the teaching robot gave it")
    robot: str | None = Field(None, description="the robot whose session taught it")
    images: int
    bytes: int = Field(description="bytes its images take in the map file")
    uses: int = Field(description="frames matched with it")
    last_used: str | None = Field(None, description="the last frame matched with it")


class MapSummary(BaseModel):
    name: str
    n_images: int
    n_features: int
    bounds: list[list[float]]
    spacing_m: float
    meta: dict[str, Any]
    checksum: str | None = Field(None, description="map version: SHA-256 of the file, the ETag")
    experiences: list[ExperienceInfo] = Field(
        default_factory=list, description="the layers the fleet learned (learning sessions)")
    build_date: str | None = None


class MapDetail(MapSummary):
    positions: list[list[float]]
    image_names: list[str]


JobState = Literal["queued", "running", "done", "failed"]
FeatureTypeName = Literal["clahe-rootsift", "sift", "xfeat", "clahe-rootsift+xfeat"]
"""A map's feature type: CLAHE + RootSIFT, the papers' SIFT, XFeat (learned, holds at night),
or CLAHE + RootSIFT and XFeat both, their similarities fused (the default)."""
MAX_FEATURES_CAP = 65_536
"""The most SIFT features per image a map build may ask to keep (``max_features``)."""
WORKING_SIDE = (32, 4096)
"""The least and the most pixels of a map's working width or height (a build's size)."""
DEFAULT_FEATURES: FeatureTypeName = "clahe-rootsift+xfeat"
"""The feature type of a map built without naming one (CLI, HTTP, Zenoh, the demo map):
both types, which measured best across light (docs/research/lighting.md)."""


class JobInfo(BaseModel):
    """A map build running on the service (``POST /maps/{name}/build``)."""

    id: str
    map: str
    state: JobState
    done: int = Field(description="images whose features are extracted")
    total: int = Field(description="images in the round")
    error: str | None = Field(None, description="why a failed job failed")
    status: int | None = Field(None, description="HTTP status of that failure")
    checksum: str | None = Field(None, description="version of the map a done job installed")
    features: FeatureTypeName = Field(DEFAULT_FEATURES, description="the map's feature type")
    max_features: int | None = Field(
        None, description="SIFT's features kept per map image and frame (0: all; None: a map "
        "of XFeat alone, which keeps its own 1,024)")
    width: int = Field(320, description="the map's working width (frames are resized to it)")
    height: int = Field(240, description="the map's working height")
    created: float
    started: float | None = None
    finished: float | None = None


class MapDeleted(BaseModel):
    map: str
    ended_sessions: list[str] = Field(description="sessions ended by ?force=true")
