"""ROS 2 over Zenoh: CDR codecs (with ``rosbags``) and the key expressions ROS 2 robots use.

Frames in (``sensor_msgs/msg/CompressedImage`` JPEG/PNG, ``sensor_msgs/msg/Image`` mono8 /
rgb8 / bgr8), estimates out (``geometry_msgs/msg/PoseWithCovarianceStamped`` and a
``diagnostic_msgs/msg/DiagnosticStatus``), and an AMCL-like initial pose in
(``PoseWithCovarianceStamped``). Payloads are raw CDR with their 4-byte encapsulation header,
as ``zenoh-bridge-ros2dds`` and ``rmw_zenoh`` carry them; (de)serialisation is ``rosbags``'
typestore, never hand-written CDR.

Two key formats (``Settings.ros2_key_format``):

- ``ros2dds`` (``zenoh-bridge-ros2dds``' default mapping): the ROS topic name without its
  leading slash, the robot namespace as its first chunks: ``robot1/camera/image_raw/compressed``.
- ``rmw_zenoh`` (its design document): ``<domain_id>/<topic>/<dds type name>/<type hash>``,
  e.g. ``0/robot1/swarmloc/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/RIHS01_..``;
  (Humble's rmw_zenoh puts ``TypeHashNotSupported`` where the hash goes);
  publications carry rmw_zenoh's attachment (int64 LE sequence number, int64 LE source
  timestamp in ns, one byte GID length = 16, 16 GID bytes).

Topic templates hold ``{robot}`` where the robot's namespace goes; it is the robot id of the
service session. Nothing here knows the estimator; the bridge hands frames to the service.
"""

from __future__ import annotations

import itertools
import logging
import math
import os
import struct
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np

try:
    from rosbags.typesys import Stores, get_typestore
except ImportError as _exc:  # the service imports this module only when ROS 2 is enabled
    raise ImportError("ROS 2 support needs the 'ros' extra: pip install 'swarmloc[ros]'"
                      ) from _exc

from service.api.errors import (
    BadRequest,
    InvalidParameters,
    PayloadTooLarge,
    ServiceError,
    UnsupportedMediaType,
)
from service.api.models import Estimate, PosePrior, check_robot_id, validated
from service.settings import Settings
from service.vision.imaging import check_size

log = logging.getLogger("swarmloc.zenoh")
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
IMAGE = "sensor_msgs/msg/Image"
POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"
STATUS = "diagnostic_msgs/msg/DiagnosticStatus"
ODOMETRY = "nav_msgs/msg/Odometry"
TF = "tf2_msgs/msg/TFMessage"

KeyFormat = Literal["ros2dds", "rmw_zenoh"]
_CHANNELS = {"mono8": 1, "rgb8": 3, "bgr8": 3}
_UNKNOWN_VAR = 1e6
_UNIFORM_YAW_VAR = math.pi**2 / 3  # variance of a heading uniform on the circle
HUMBLE_TYPE_HASH = "TypeHashNotSupported"  # rmw_zenoh on Humble has no type hashes
_ATTACHMENT = struct.Struct("<qqB16s")  # rmw_zenoh: seq, source timestamp (ns), GID len, GID


def make_typestore() -> Any:
    """The ROS 2 Humble message types (the std messages we use are the same in later
    distributions, byte for byte and by RIHS01 hash)."""
    return get_typestore(Stores.ROS2_HUMBLE)


@dataclass(frozen=True)
class Stamp:
    """``builtin_interfaces/msg/Time``, kept exact so the answer echoes the frame's stamp."""

    sec: int
    nanosec: int

    @property
    def seconds(self) -> float:
        return self.sec + 1e-9 * self.nanosec

    @classmethod
    def from_seconds(cls, t: float) -> Stamp:
        sec = math.floor(t)
        return cls(int(sec), min(round((t - sec) * 1e9), 999_999_999))


@dataclass(frozen=True)
class RosFrame:
    """A validated frame: encoded bytes (CompressedImage) or 8-bit grayscale pixels (Image)."""

    data: bytes | np.ndarray
    content_type: str | None
    stamp: Stamp
    frame_id: str


def yaw_variance(speed: float, speed_sigma: float, lost: bool = False) -> float:
    """Variance (rad²) of the yaw we report. The heading is the direction of motion, so its
    error is about atan(σ_v / speed); below σ_v (standing, or lost) any direction is as good
    as another and we report the variance of a uniform heading, π²/3."""
    if lost or not math.isfinite(speed) or speed <= speed_sigma:
        return _UNIFORM_YAW_VAR
    return math.atan2(speed_sigma, speed) ** 2


def initial_pose_radius(cov_xx: float, cov_yy: float, minimum: float = 1.0) -> float:
    """Search radius of an initial pose: two standard deviations of its larger axis (95 % of
    a Gaussian), at least ``minimum`` metres; AMCL spreads its particles the same way."""
    var = max(cov_xx, cov_yy)
    if not math.isfinite(var) or var < 0:
        raise InvalidParameters(f"initial pose covariance has a variance of {var}")
    return float(min(max(2.0 * math.sqrt(var), minimum), 10_000.0))


class Codec:
    """CDR (de)serialisation of the messages the service speaks, with clear errors."""

    def __init__(self, typestore: Any | None = None) -> None:
        self.store = typestore or make_typestore()
        self.types = self.store.types

    # ---- generic ------------------------------------------------------------------------
    def deserialize(self, payload: bytes, typename: str) -> Any:
        if len(payload) < 4:
            raise BadRequest(f"{len(payload)} bytes are not a CDR {typename} message "
                             "(it has no 4-byte encapsulation header)")
        try:
            return self.store.deserialize_cdr(payload, typename)
        except Exception as exc:  # rosbags raises SerdeError, or struct/index errors
            raise BadRequest(f"payload is not a CDR-encoded {typename} (wrong type or "
                             f"truncated message): {exc}") from None

    def serialize(self, msg: Any, typename: str) -> bytes:
        return bytes(self.store.serialize_cdr(msg, typename))

    def type_hash(self, typename: str) -> str:
        """REP-2011 RIHS01 hash, as rmw_zenoh puts it in its key expressions."""
        return str(self.store.hash_rihs01(typename))

    # ---- frames in ----------------------------------------------------------------------
    def frame(self, payload: bytes, typename: str, max_bytes: int, max_pixels: int,
              min_side: int = 1) -> RosFrame:
        if len(payload) > max_bytes:
            raise PayloadTooLarge(f"frame message is {len(payload)} bytes; the limit is "
                                  f"{max_bytes} bytes")
        msg = self.deserialize(payload, typename)
        stamp = Stamp(int(msg.header.stamp.sec), int(msg.header.stamp.nanosec))
        if typename == COMPRESSED_IMAGE:
            return RosFrame(msg.data.tobytes(), compressed_content_type(msg.format), stamp,
                            msg.header.frame_id)
        return RosFrame(raw_image(msg, max_pixels, min_side), None, stamp,
                        msg.header.frame_id)

    # ---- estimates out ------------------------------------------------------------------
    def _header(self, stamp: Stamp, frame_id: str) -> Any:
        t = self.types
        return t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=stamp.sec, nanosec=stamp.nanosec),
            frame_id=frame_id)

    def pose(self, est: Estimate, stamp: Stamp, frame_id: str, speed_sigma: float) -> bytes:
        t = self.types
        cov = np.array(est.pose_covariance, dtype=np.float64)
        if cov[35] >= _UNKNOWN_VAR:  # the estimator gave no yaw variance: ours (see above)
            cov[35] = yaw_variance(est.speed, speed_sigma, est.lost)
        half = 0.5 * est.heading
        pose = t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=est.x, y=est.y, z=0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(half),
                                                          w=math.cos(half)))
        msg = t[POSE](header=self._header(stamp, frame_id),
                      pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov))
        return self.serialize(msg, POSE)

    def odometry(self, payload: bytes) -> tuple[float, tuple[float, float, float], str]:
        """(stamp s, (x, y, yaw) of odom->base_link, the odometry frame's id) of a
        nav_msgs/Odometry; InvalidParameters for a non-finite pose."""
        msg = self.deserialize(payload, ODOMETRY)
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        pose = (float(p.x), float(p.y), quaternion_yaw(q))
        if not all(math.isfinite(v) for v in pose):
            raise InvalidParameters("odometry pose must be finite")
        st = msg.header.stamp
        return Stamp(int(st.sec), int(st.nanosec)).seconds, pose, \
            _text(msg.header.frame_id) or "odom"

    def map_to_odom(self, est: Estimate, odom: tuple[float, float, float], stamp: Stamp,
                    map_frame: str, odom_frame: str) -> bytes:
        """TFMessage with map->odom = map->base_link o (odom->base_link)^-1, as AMCL
        publishes it: the robot's odometry composed with it gives the estimate."""
        x, y, yaw = map_to_odom((est.x, est.y, est.heading), odom)
        t = self.types
        half = 0.5 * yaw
        tf = t["geometry_msgs/msg/TransformStamped"](
            header=self._header(stamp, map_frame), child_frame_id=odom_frame,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=x, y=y, z=0.0),
                rotation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(half),
                                                           w=math.cos(half))))
        return self.serialize(t[TF](transforms=[tf]), TF)

    def status(self, robot: str, body: dict[str, Any]) -> bytes:
        """DiagnosticStatus of one answer: level OK (tracking), WARN (initializing,
        recovering), ERROR (lost, or a rejected input); values carry the numbers."""
        t = self.types
        cls = t[STATUS]
        if "error" in body:
            level, message = cls.ERROR, str(body["error"])
            values = {"error": body["error"], "http_status": body.get("status"),
                      "input_seq": body.get("input_seq")}
        else:
            status = body["status"]
            level = (cls.ERROR if body["lost"] else cls.OK if status == "tracking"
                     else cls.WARN)
            message = status
            values = {k: body.get(k) for k in ("status", "lost", "speed", "score",
                                               "comparisons", "accuracy_m", "x", "y",
                                               "heading", "seq", "input_seq", "frame_id")}
        kv = [t["diagnostic_msgs/msg/KeyValue"](key=k, value=_text(v))
              for k, v in values.items()]
        msg = cls(level=level, name="swarmloc", message=message, hardware_id=robot, values=kv)
        return self.serialize(msg, STATUS)

    # ---- initial pose in ----------------------------------------------------------------
    def initial_pose(self, payload: bytes) -> tuple[PosePrior, str]:
        """(position prior, frame_id) of a PoseWithCovarianceStamped, like AMCL's."""
        msg = self.deserialize(payload, POSE)
        p = msg.pose.pose.position
        cov = np.asarray(msg.pose.covariance, dtype=np.float64)
        if not (math.isfinite(p.x) and math.isfinite(p.y)):
            raise InvalidParameters(f"initial pose ({p.x}, {p.y}) is not finite")
        radius = initial_pose_radius(float(cov[0]), float(cov[7])) if len(cov) > 7 else 1.0
        prior = validated(PosePrior, {"x": float(p.x), "y": float(p.y), "radius": radius},
                          "initial pose")
        return prior, str(msg.header.frame_id)


def quaternion_yaw(q: Any) -> float:
    """Yaw (rad, about z) of a geometry_msgs/Quaternion."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def map_to_odom(map_base: tuple[float, float, float], odom_base: tuple[float, float, float]
                ) -> tuple[float, float, float]:
    """(x, y, yaw) of map->odom = map->base_link o (odom->base_link)^-1 (planar)."""
    yaw = map_base[2] - odom_base[2]
    c, s = math.cos(yaw), math.sin(yaw)
    return (map_base[0] - (c * odom_base[0] - s * odom_base[1]),
            map_base[1] - (s * odom_base[0] + c * odom_base[1]),
            math.atan2(math.sin(yaw), math.cos(yaw)))


class OdometryBuffer:
    """The last Odometry messages of each robot, for the frame stamped nearest to them."""

    def __init__(self, keep: int = 256, max_robots: int = 10_000) -> None:
        self.keep = keep
        self.max_robots = max_robots
        self._lock = threading.Lock()
        self._by_robot: dict[str, deque[tuple[float, tuple[float, float, float], str]]] = {}

    def add(self, robot: str, t: float, pose: tuple[float, float, float], frame: str) -> None:
        with self._lock:
            buf = self._by_robot.get(robot)
            if buf is None:
                if len(self._by_robot) >= self.max_robots:
                    return
                buf = self._by_robot[robot] = deque(maxlen=self.keep)
            buf.append((t, pose, frame))

    def nearest(self, robot: str, t: float, max_age_s: float
                ) -> tuple[tuple[float, float, float], str] | None:
        """The pose (and odometry frame) of the message nearest ``t``, within
        ``max_age_s``; None where none is."""
        with self._lock:
            buf = list(self._by_robot.get(robot, ()))
        if not buf:
            return None
        best = min(buf, key=lambda m: abs(m[0] - t))
        return (best[1], best[2]) if abs(best[0] - t) <= max_age_s else None


def compressed_content_type(fmt: str) -> str | None:
    """Media type of a CompressedImage ``format`` ("jpeg", "png", "bgr8; jpeg compressed
    bgr8", ...); None when empty (the bytes are sniffed); 415 for other formats."""
    f = fmt.strip().lower()
    if not f:
        return None
    if "compresseddepth" in f:
        raise UnsupportedMediaType(f"CompressedImage format '{fmt}' is a depth image; send "
                                   "a camera image in jpeg or png")
    if "jpeg" in f or "jpg" in f:
        return "image/jpeg"
    if "png" in f:
        return "image/png"
    raise UnsupportedMediaType(f"CompressedImage format '{fmt}' is not supported; "
                               "send jpeg or png")


def raw_image(msg: Any, max_pixels: int, min_side: int = 1) -> np.ndarray:
    """8-bit grayscale pixels of a sensor_msgs/Image after checking its geometry."""
    enc = str(msg.encoding).strip().lower()
    if enc not in _CHANNELS:
        raise UnsupportedMediaType(f"Image encoding '{msg.encoding}' is not supported; "
                                   f"send one of {sorted(_CHANNELS)} or a CompressedImage")
    w, h, step, ch = int(msg.width), int(msg.height), int(msg.step), _CHANNELS[enc]
    check_size(w, h, max_pixels, max(min_side, 1))
    if step < w * ch:
        raise BadRequest(f"Image step {step} is smaller than width x channels = {w * ch} "
                         f"for {enc}")
    if len(msg.data) != step * h:
        raise BadRequest(f"Image data has {len(msg.data)} bytes; step x height = "
                         f"{step} x {h} = {step * h}")
    rows = np.asarray(msg.data, dtype=np.uint8).reshape(h, step)[:, : w * ch]
    if ch == 1:
        return np.ascontiguousarray(rows)
    code = cv2.COLOR_RGB2GRAY if enc == "rgb8" else cv2.COLOR_BGR2GRAY
    return cv2.cvtColor(np.ascontiguousarray(rows.reshape(h, w, 3)), code)


def _text(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


# ---- key expressions --------------------------------------------------------------------
def dds_type_name(typename: str) -> str:
    """``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_`` (the DDS type name)."""
    pkg, kind, name = typename.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


@dataclass(frozen=True)
class TopicKey:
    """One topic template (``{robot}/camera/image_raw/compressed``) as Zenoh keys."""

    template: str
    typename: str
    key_format: KeyFormat = "ros2dds"
    domain_id: int = 0
    type_hash: str = ""
    default_robot: str = "robot"

    @property
    def chunks(self) -> list[str]:
        return self.template.strip("/").split("/")

    def key(self, robot: str) -> str:
        topic = "/".join(robot if c == "{robot}" else c for c in self.chunks)
        if self.key_format == "rmw_zenoh":
            return f"{self.domain_id}/{topic}/{dds_type_name(self.typename)}/{self.type_hash}"
        return topic

    def subscription(self) -> str:
        """Key expression matching every robot's topic (any type hash with rmw_zenoh)."""
        topic = "/".join("*" if c == "{robot}" else c for c in self.chunks)
        if self.key_format == "rmw_zenoh":
            return f"{self.domain_id}/{topic}/{dds_type_name(self.typename)}/*"
        return topic

    def robot(self, key: str) -> str:
        parts = str(key).split("/")
        if self.key_format == "rmw_zenoh":
            parts = parts[1:-2]
        try:
            return parts[self.chunks.index("{robot}")]
        except ValueError:
            return self.default_robot


def rmw_attachment(seq: int, gid: bytes, t_ns: int | None = None) -> bytes:
    """rmw_zenoh's publication attachment: seq, source timestamp (ns since epoch), GID."""
    if len(gid) != 16:
        raise ValueError("an rmw_zenoh GID has 16 bytes")
    return _ATTACHMENT.pack(seq, time.time_ns() if t_ns is None else t_ns, 16, gid)


def parse_rmw_attachment(raw: bytes | None) -> tuple[int, int, bytes] | None:
    """(seq, timestamp ns, GID) of an rmw_zenoh attachment, None when absent or another
    layout (the attachment is optional metadata: a frame is not rejected for it)."""
    if raw is None or len(raw) != _ATTACHMENT.size:
        return None
    seq, t_ns, n, gid = _ATTACHMENT.unpack(raw)
    return (seq, t_ns, gid) if n == 16 else None


# ---- the endpoints the Zenoh bridge declares ----------------------------------------------
SubmitFrame = Callable[[str, "bytes | np.ndarray", dict[str, Any], str | None,
                        Callable[[dict[str, Any]], None]], None]
# the bridge's control workers (service/zenoh/workers.py): (robot, run, refuse)
SubmitControl = Callable[[str, Callable[[], None], Callable[[ServiceError], None]], None]


class Ros2Endpoints:
    """Subscribers for frames and initial poses, publishers for pose and status.

    ``submit(robot, data, meta, content_type, reply)`` queues a frame in the bridge's
    newest-wins slot; ``reply(body)`` is called with the bridge's JSON answer (an Estimate
    or an error body), which is then also published here as ROS messages.
    ``publish_json(robot, body)`` publishes on the JSON estimate key (errors go there too,
    exactly as on the JSON path). ``control(robot, run, refuse)`` queues an initial pose's
    reset to the bridge's control workers, after the robot's control queries: Zenoh runs the
    initialpose subscriber's callback on one thread for every robot, fed by a bounded queue,
    so a reset that waits there (its session held, the learner draining its queue) held every
    other robot's reset, and once that queue was full, every frame on the link.
    """

    def __init__(self, settings: Settings, service: Any, submit: SubmitFrame,
                 publish_json: Callable[[str, dict[str, Any]], None],
                 control: SubmitControl) -> None:
        self.settings = settings
        self.service = service
        self.submit = submit
        self.publish_json = publish_json
        self.control = control
        self.codec = Codec()
        s = settings

        def topic(template: str, typename: str) -> TopicKey:
            type_hash = HUMBLE_TYPE_HASH if s.ros2_distro == "humble" \
                else self.codec.type_hash(typename)
            return TopicKey(template, typename, s.ros2_key_format, s.ros2_domain_id,
                            type_hash, s.ros2_default_robot)

        self.frames = [topic(tpl, typ) for tpl, typ in
                       ((s.ros2_compressed_image_topic, COMPRESSED_IMAGE),
                        (s.ros2_image_topic, IMAGE)) if tpl]
        self.initialpose = topic(s.ros2_initialpose_topic, POSE) \
            if s.ros2_initialpose_topic else None
        self.pose_key = topic(s.ros2_pose_topic, POSE)
        self.status_key = topic(s.ros2_status_topic, STATUS)
        self.odom_key = topic(s.ros2_odom_topic, ODOMETRY) if s.ros2_odom_topic else None
        self.tf_key = topic(s.ros2_tf_topic, TF) if s.ros2_tf_topic else None
        self.odometry = OdometryBuffer()
        self._session: Any = None
        self._gid = os.urandom(16)  # this publisher's rmw_zenoh GID
        self._seq = itertools.count(1)  # rmw_zenoh sequence numbers (thread-safe next)

    def declare(self, session: Any) -> list[Any]:
        self._session = session
        decls = [session.declare_subscriber(k.subscription(), self._frame_handler(k))
                 for k in self.frames]
        if self.initialpose is not None:
            decls.append(session.declare_subscriber(self.initialpose.subscription(),
                                                    self._on_initialpose))
        if self.odom_key is not None:
            decls.append(session.declare_subscriber(self.odom_key.subscription(),
                                                    self._on_odometry))
        return decls

    # ---- publishing ---------------------------------------------------------------------
    def _put(self, key: str, payload: bytes) -> None:
        if self._session is None:
            return
        if self.settings.ros2_key_format == "rmw_zenoh":
            self._session.put(key, payload,
                              attachment=rmw_attachment(next(self._seq), self._gid))
        else:
            self._session.put(key, payload)

    def frame_id(self, est: Estimate) -> str:
        return self.settings.ros2_frame_id or est.frame_id

    def publish(self, robot: str, body: dict[str, Any], stamp: Stamp | None,
                odom: tuple[tuple[float, float, float], str] | None = None) -> None:
        """The ROS answer to one input: the pose (estimates only), map->odom on tf where
        the frame carried odometry, and the status."""
        if "error" not in body:
            est = Estimate.model_validate(body)
            st = stamp or Stamp.from_seconds(est.stamp or 0.0)
            self._put(self.pose_key.key(robot),
                      self.codec.pose(est, st, self.frame_id(est),
                                      self.settings.ros2_speed_sigma_mps))
            if odom is not None and self.tf_key is not None:
                self._put(self.tf_key.key(robot),
                          self.codec.map_to_odom(est, odom[0], st, self.frame_id(est),
                                                 odom[1]))
        self._put(self.status_key.key(robot), self.codec.status(robot, body))

    def _reject(self, robot: str, exc: Any, seq: int | None = None) -> None:
        self.service.metrics.rejected.labels(type(exc).__name__).inc()
        self._report(robot, exc, seq)

    def _report(self, robot: str, exc: Any, seq: int | None = None) -> None:
        """Publish an error: on the JSON estimate key and as the status."""
        from service.zenoh.replies import error_body

        body = error_body(exc, robot, seq)
        self.publish_json(robot, body)
        self.publish(robot, body, None)

    # ---- subscribers --------------------------------------------------------------------
    def _frame_handler(self, topic: TopicKey) -> Callable[[Any], None]:
        def on_frame(sample: Any) -> None:
            robot = topic.robot(str(sample.key_expr))
            att = parse_rmw_attachment(sample.attachment.to_bytes()
                                       if sample.attachment else None)
            seq = att[0] if att else None
            try:
                frame = self.codec.frame(sample.payload.to_bytes(), topic.typename,
                                         self.settings.max_body_bytes,
                                         self.settings.max_pixels,
                                         self.settings.min_frame_side)
            except ServiceError as exc:
                self._reject(robot, exc, seq)
                return
            meta: dict[str, Any] = {"t": frame.stamp.seconds, "seq": seq}
            odom = self.odometry.nearest(robot, frame.stamp.seconds,
                                         self.settings.ros2_odom_max_age_s)
            if odom is not None:
                meta["odom"] = dict(zip(("x", "y", "yaw"), odom[0], strict=True))
            self.submit(robot, frame.data, meta, frame.content_type,
                        lambda body: self.publish(robot, body, frame.stamp, odom))

        return on_frame

    def _on_odometry(self, sample: Any) -> None:
        assert self.odom_key is not None
        robot = self.odom_key.robot(str(sample.key_expr))
        try:
            check_robot_id(robot)
            t, pose, frame = self.codec.odometry(sample.payload.to_bytes())
        except ServiceError as exc:  # not an Odometry message, or a non-finite pose
            self._reject(robot, exc)
            return
        self.odometry.add(robot, t, pose, frame)

    def _on_initialpose(self, sample: Any) -> None:
        """Decode an initial pose and queue its reset to the control workers (the robot's
        after its earlier ones): this callback thread never waits for the service."""
        assert self.initialpose is not None
        robot = self.initialpose.robot(str(sample.key_expr))
        try:
            check_robot_id(robot)
            prior, frame_id = self.codec.initial_pose(sample.payload.to_bytes())
        except ServiceError as exc:
            self._reject(robot, exc)
            return
        self.control(robot, lambda: self._reset(robot, prior, frame_id),
                     lambda exc: self._report(robot, exc))  # 503: too many wait, shutdown

    def _reset(self, robot: str, prior: PosePrior, frame_id: str) -> None:
        from service.zenoh.replies import internal_error

        try:
            session = (self.service.ensure_session(robot)
                       if self.settings.zenoh_creates_sessions
                       else self.service.session(robot))
            expected = self.settings.ros2_frame_id or session.localizer.map.name
            if frame_id and frame_id not in (expected, "map"):
                raise InvalidParameters(f"initial pose is in frame '{frame_id}'; send it in "
                                        f"'{expected}' (the map frame)")
            info = self.service.reset_session(robot, prior)
        except ServiceError as exc:
            self._reject(robot, exc)
            return
        except Exception as exc:  # never leave the robot without an answer
            log.exception("the initial pose of robot %s failed", robot)
            self._reject(robot, internal_error(exc))
            return
        msg = (f"reset near ({prior.x:.2f}, {prior.y:.2f}) within {prior.radius:.2f} m "
               f"on map {info.map}")
        t = self.codec.types
        cls = t[STATUS]
        kv = [t["diagnostic_msgs/msg/KeyValue"](key=k, value=_text(v)) for k, v in
              (("status", "initializing"), ("x", prior.x), ("y", prior.y),
               ("radius", prior.radius))]
        self._put(self.status_key.key(robot), self.codec.serialize(
            cls(level=cls.OK, name="swarmloc", message=msg, hardware_id=robot, values=kv),
            STATUS))
