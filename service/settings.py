"""Service configuration from environment variables (prefix SWARMLOC_) or CLI flags."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from service.api.models import EstimatorName, Matcher


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="SWARMLOC_", env_nested_delimiter="__")

    host: str = Field("127.0.0.1", description="HTTP bind address (default: loopback only, "
                      "or 0.0.0.0 when auth_token is set; give it to serve other hosts)")
    port: int = Field(8080, description="HTTP port")
    maps_dir: Path = Field(Path("maps"), description="directory of *.swmap files to load")
    default_map: str | None = Field(None, description="map for sessions that name none "
                                    "(default: the only map, or 'demo')")
    default_estimator: EstimatorName = "dpso"
    max_sessions: int = Field(256, description="most concurrent robot sessions")
    session_idle_s: float = Field(600.0, description="idle sessions expire after this")
    # where sessions live (service/engine/store.py): a SQLite file (durable), this process's
    # memory, or Redis shared by replicas
    session_store: str = Field(
        "sqlite", description="'sqlite' (default: MAPS_DIR/sessions.sqlite, every applied "
        "frame kept across a crash or kill -9), sqlite:///relative/path or "
        "sqlite:////absolute/path (?synchronous=full: also across power loss), 'memory' "
        "(in-process, lost on a crash) or redis://host:port/db (shared by several replicas)")
    maps_sync: Literal["directory", "redis"] = Field(
        "directory", description="how replicas share their maps: 'directory' (one maps "
        "directory, e.g. one volume) or 'redis' (a maps directory each, on any machine: map "
        "files travel through the Redis session store)")
    session_snapshot: Path | None = Field(None, description="'memory' store: write the "
                                          "sessions here on SIGTERM, read them at start")
    session_lock_lease_s: float = Field(10.0, gt=0, description="Redis: a robot's lock "
                                        "expires this long after a crashed holder took it")
    session_lock_wait_s: float = Field(5.0, ge=0, description="Redis: the longest a frame "
                                       "waits for its robot's lock (then 409)")
    zenoh_claim_lease_s: float = Field(5.0, gt=0, description="Redis: a replica serves a "
                                       "robot's Zenoh traffic until this passes without any")
    replica_id: str | None = Field(None, description="this replica's name in Redis claims "
                                   "(default: host name and process id)")
    max_body_bytes: int = Field(8 * 1024 * 1024, description="largest accepted frame body")
    max_pixels: int = Field(16_000_000, description="largest accepted image (width*height)")
    max_map_bytes: int = Field(1 << 30, description="largest map upload (PUT /maps/NAME)")
    max_archive_bytes: int = Field(2 << 30, description="largest round archive to build from")
    max_archive_members: int = Field(100_000, description="most files in a round archive")
    max_unpacked_bytes: int = Field(4 << 30, description="most bytes a round archive unpacks to")
    max_archive_ratio: float = Field(100.0, description="largest unpacked/packed ratio "
                                     "(beyond: a zip bomb)")
    build_duty: float = Field(0.5, gt=0, le=1, description="share of the time a map build "
                              "works; it sleeps the rest so robots keep their frame rate")
    experience_budget_mb: float = Field(
        64.0, ge=0, description="most megabytes the learned experiences of one map take in its "
        "file; beyond, the least used experience is retired first")
    learn_commit_images: int = Field(
        40, ge=1, description="a learning session's collected images are written into its map "
        "(a new version) when this many are collected, and when the session ends or is reset")
    learn_accuracy_m: float = Field(
        1.5, gt=0, description="a learning session's frame teaches only with accuracy_m "
        "at most this")
    learn_weak_ratio: float = Field(
        0.4, gt=0, le=1, description="a frame teaches only where the map's layers match it "
        "weakly: their best similarity below this share of the map's same-light level (how "
        "well its consecutive images match each other)")
    auth_token: str | None = Field(None, description="if set, HTTP needs 'Bearer <token>'")
    workers: int = Field(0, description="frame-processing threads (0: 2 x number of CPUs)")
    numba_cache_dir: Path | None = Field(
        None, description="where the matcher's compiled kernels are kept between starts "
        "(default: $XDG_CACHE_HOME/swarmloc/numba, else ~/.cache/swarmloc/numba; never the "
        "installed package). Unwritable: they compile at each start (seconds, before the "
        "service reports ready)")
    matcher: Matcher = Field(
        "auto", description="how a frame's features are compared with a map image's: "
        "'exact' every pair (the papers' similarity), 'words' only the pairs that share a "
        "visual word of the map (an inverted file trained from the map's own features at "
        "load, seeded: less work per comparison, nearly the same matches; RootSIFT maps), "
        "'auto' words on a map whose images hold more than 2,048 RootSIFT features (the "
        "median image; built with a cap above the default), where every pair grows with the "
        "square of the features, exact on every other map")
    image_cache_mb: int = Field(
        512, ge=0, le=2**20, description="per map: memory for its images' descriptors as the "
        "matchers take them (made on first use, the least recently used dropped beyond this "
        "and made again when needed). 512 MiB holds every image of a ~1,000-image map of "
        "both feature types; unbounded, a large map's share grew with the area visited")
    warm_geometry: bool = Field(
        True, description="build each map's two-view geometry structures in the background "
        "after it is loaded (half a core, maps of up to 4,096 images), so that the first frames "
        "located at an image do not build them (on a rendered dusk round, localizer step p50 "
        "29 ms with them built against 79 ms on a first pass without)")
    opencv_threads: int = Field(1, ge=0, description="OpenCV's own threads per call (0: its "
                                "default, all CPUs); frames already run in parallel threads")
    # ---- hardening: cost ceilings, input bounds, shutdown (README "Hardening")
    max_particles: int = Field(20_000, ge=2, description="most particles a session may ask "
                               "for (per-session cost ceiling; a frame's cost grows with it)")
    heavy_particles: int = Field(2000, ge=2, description="sessions with more particles run "
                                 "in their own quarter of the frame workers (fair scheduling)")
    pose_margin_m: float = Field(1000.0, ge=0, description="pose priors, resets and initial "
                                 "poses must lie within the map's extent plus this margin (m)")
    min_frame_side: int = Field(16, ge=1, description="smallest accepted frame width/height "
                                "(px): smaller frames cannot carry features")
    http_max_header_bytes: int = Field(8192, ge=1024, description="longest HTTP request "
                                       "line plus headers (bytes); longer: 431")
    http_read_timeout_s: float = Field(30.0, gt=0, description="an HTTP request's head must "
                                       "arrive, and its body may pause, at most this long "
                                       "(s); then the connection is closed (slowloris)")
    shutdown_deadline_s: float = Field(10.0, gt=0, description="at shutdown, frames in "
                                       "flight get this long to finish; new frames get 503")
    # ---- Zenoh (service/zenoh/config.py builds the config; a file is the way to configure
    # TLS/mTLS, user/password and access control)
    zenoh_enabled: bool = True
    zenoh_config_file: Path | None = Field(
        None, description="a Zenoh JSON5 config file (TLS, usrpwd, access_control, ...); the "
        "zenoh_* settings below apply on top of it only where set explicitly")
    zenoh_mode: Literal["peer", "client", "router"] = "peer"
    zenoh_connect: list[str] = Field(default_factory=list, description="e.g. tcp/10.0.0.2:7447")
    zenoh_listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"],
                                    description="safe default: loopback only")
    zenoh_multicast_scouting: bool = Field(False, description="multicast discovery (off by "
                                           "default: it announces the service on the LAN)")
    zenoh_prefix: str = "swarmloc"
    zenoh_unauthenticated: bool = Field(
        False, description="accept starting Zenoh without a config file while HTTP needs a "
        "token (Zenoh would then bypass the token; refused by default)")
    zenoh_create_sessions: bool | None = Field(
        None, description="a Zenoh frame for an unknown robot creates its session (default: "
        "yes without SWARMLOC_AUTH_TOKEN, no with it)")
    # ROS 2 over Zenoh (service/zenoh/ros2.py): topic templates, {robot} = the robot's namespace
    ros2_enabled: bool = Field(False, description="serve ROS 2 CDR messages on Zenoh too")
    ros2_key_format: Literal["ros2dds", "rmw_zenoh"] = Field(
        "ros2dds", description="zenoh-bridge-ros2dds keys, or rmw_zenoh's "
        "<domain>/<topic>/<type>/<hash> keys with its attachment")
    ros2_domain_id: int = Field(0, ge=0, description="ROS_DOMAIN_ID (rmw_zenoh keys only)")
    ros2_distro: Literal["humble", "jazzy"] = Field(
        "jazzy", description="rmw_zenoh type hash in published keys: RIHS01 (jazzy and "
        "later) or Humble's 'TypeHashNotSupported'")
    ros2_compressed_image_topic: str = Field(
        "{robot}/camera/image_raw/compressed",
        description="sensor_msgs/CompressedImage frames in ('' disables)")
    ros2_image_topic: str = Field("{robot}/camera/image_raw",
                                  description="sensor_msgs/Image frames in ('' disables)")
    ros2_pose_topic: str = Field("{robot}/swarmloc/pose",
                                 description="geometry_msgs/PoseWithCovarianceStamped out")
    ros2_status_topic: str = Field("{robot}/swarmloc/status",
                                   description="diagnostic_msgs/DiagnosticStatus out")
    ros2_initialpose_topic: str = Field(
        "{robot}/initialpose",
        description="geometry_msgs/PoseWithCovarianceStamped in: reset near it ('' disables)")
    ros2_odom_topic: str = Field(
        "{robot}/odom", description="nav_msgs/Odometry in: each frame takes the message "
        "nearest its stamp as its odometry ('' disables)")
    ros2_odom_max_age_s: float = Field(
        0.5, gt=0, description="an Odometry message farther than this from a frame's stamp "
        "is not used for it, s")
    ros2_tf_topic: str = Field(
        "tf", description="tf2_msgs/TFMessage out: map->odom (as AMCL) for frames that "
        "carry odometry ('' disables)")
    ros2_default_robot: str = Field("robot", description="robot id when a topic template "
                                    "has no {robot}")
    ros2_frame_id: str | None = Field(None, description="frame_id of the poses "
                                      "(default: the map name)")
    ros2_speed_sigma_mps: float = Field(
        0.3, gt=0, description="speed uncertainty behind the reported yaw variance: "
        "atan(sigma / speed)^2, uniform (pi^2/3) below sigma")

    @model_validator(mode="after")
    def _maps_through_redis(self) -> Settings:
        if self.maps_sync == "redis" and \
                not self.session_store.startswith(("redis://", "rediss://", "unix://")):
            raise ValueError("maps_sync 'redis' needs the Redis session store "
                             "(SWARMLOC_SESSION_STORE=redis://host:port/db); one service "
                             "alone, or replicas on one maps directory, need 'directory'")
        return self

    @model_validator(mode="after")
    def _bind_address(self) -> Settings:
        """Safe by default: loopback unless the host is given or a token guards the HTTP API
        (Zenoh listens on loopback unless its endpoints or a config file say otherwise)."""
        if "host" not in self.model_fields_set and self.auth_token:
            self.host = "0.0.0.0"
        return self

    @property
    def frame_workers(self) -> int:
        """Threads that process frames, per transport (frames wait in OpenCV/BLAS most of
        the time with the GIL released, so twice the CPUs keeps them busy)."""
        return self.workers or 2 * (os.cpu_count() or 1)

    @property
    def zenoh_creates_sessions(self) -> bool:
        if self.zenoh_create_sessions is not None:
            return self.zenoh_create_sessions
        return not self.auth_token
