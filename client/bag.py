"""rosbag2 recordings (sqlite3 or MCAP, read with ``rosbags``) -> a round of the dataset format.

Images come from one ``sensor_msgs/msg/CompressedImage`` (JPEG/PNG, written as they are) or
``sensor_msgs/msg/Image`` topic (mono8/rgb8/bgr8, written as grayscale PNG, the service's
working format); their time is ``header.stamp`` (the bag's receive time when the stamp is 0).
Positions come from a ``sensor_msgs/msg/NavSatFix`` topic (lat/lon; fixes with status
NO_FIX are dropped) or from a ``nav_msgs/msg/Odometry``, ``geometry_msgs/msg/PoseStamped`` or
``geometry_msgs/msg/PoseWithCovarianceStamped`` topic (x/y metres), linearly interpolated to
each image's stamp; images outside the positions' time span are left out (no extrapolation).
Optionally only an image every ``min_distance`` metres of travelled path is kept (the papers
record one about every 0.6 m). With an ``odom_topic`` (``nav_msgs/msg/Odometry``, the
robot's wheel odometry), each written image also gets the odometry pose (x, y, yaw)
interpolated to its stamp (clamped at the ends of the topic's span) in ``odometry.csv``.

A geographic round is written as ``image,lat,lon,t``. Rounds of one dataset must share a local
frame, so the dataset's ``dataset.json`` ``origin`` is used, and written from the first fix
when the dataset has none. Needs the ``ros`` extra (``pip install 'swarmloc[ros]'``).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from client.dataset import DATASET_FILE, write_dataset_meta, write_odometry, write_round
from service.api.geo import LocalFrame

NAVSATFIX = "sensor_msgs/msg/NavSatFix"
POSE_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped",
              "geometry_msgs/msg/PoseWithCovarianceStamped")
BAG_SUFFIXES = (".mcap", ".db3")


class BagError(ValueError):
    """The bag cannot be converted; the message says what is missing or wrong."""


@dataclass(frozen=True)
class Conversion:
    path: Path
    images: int  # written
    outside: int  # stamps outside the positions' time span, or going backwards
    subsampled: int  # dropped by --min-distance
    geographic: bool
    origin: tuple[float, float] | None
    length_m: float  # travelled path of the written images


def is_bag(path: str | Path) -> bool:
    """A rosbag2 directory (with metadata.yaml) or a single .mcap / .db3 storage file."""
    p = Path(path)
    return (p.is_dir() and (p / "metadata.yaml").is_file()) or (
        p.is_file() and p.suffix.lower() in BAG_SUFFIXES)


def _stamp(msg: Any, bag_ns: int) -> float:
    st = msg.header.stamp
    t = int(st.sec) + 1e-9 * int(st.nanosec)
    return t if t > 0 else 1e-9 * bag_ns


def _connections(reader: Any, topic: str, allowed: tuple[str, ...]) -> list[Any]:
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        topics = sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections})
        raise BagError(f"topic '{topic}' is not in the bag; it has: {', '.join(topics)}")
    bad = {c.msgtype for c in conns} - set(allowed)
    if bad:
        raise BagError(f"topic '{topic}' has type {', '.join(sorted(bad))}; expected "
                       f"{' or '.join(allowed)}")
    return conns


def _positions(reader: Any, store: Any, topic: str) -> tuple[np.ndarray, np.ndarray, bool]:
    """(times, (N, 2) values, geographic): lat/lon of a NavSatFix topic, else x/y."""
    conns = _connections(reader, topic, (NAVSATFIX, *POSE_TYPES))
    geographic = conns[0].msgtype == NAVSATFIX
    times, values = [], []
    for conn, t_ns, raw in reader.messages(connections=conns):
        msg = store.deserialize_cdr(raw, conn.msgtype)
        if geographic:
            if msg.status.status < 0:  # STATUS_NO_FIX
                continue
            v = (msg.latitude, msg.longitude)
        else:
            pose = msg.pose.pose if conn.msgtype != "geometry_msgs/msg/PoseStamped" \
                else msg.pose
            v = (pose.position.x, pose.position.y)
        if np.all(np.isfinite(v)):
            times.append(_stamp(msg, t_ns))
            values.append(v)
    if len(times) < 2:
        raise BagError(f"topic '{topic}' has {len(times)} usable positions; at least 2 are "
                       "needed to interpolate")
    order = np.argsort(times, kind="stable")
    t, vals = np.asarray(times)[order], np.asarray(values, float)[order]
    keep = np.concatenate([np.diff(t) > 0, [True]])  # one position per time (the last)
    return t[keep], vals[keep], geographic


def _odometry(reader: Any, store: Any, topic: str) -> tuple[np.ndarray, np.ndarray]:
    """(times, (N, 3) x, y, unwrapped yaw) of a nav_msgs/Odometry topic."""
    from service.zenoh.ros2 import quaternion_yaw

    conns = _connections(reader, topic, ("nav_msgs/msg/Odometry",))
    times, values = [], []
    for conn, t_ns, raw in reader.messages(connections=conns):
        msg = store.deserialize_cdr(raw, conn.msgtype)
        pose = msg.pose.pose
        v = (pose.position.x, pose.position.y, quaternion_yaw(pose.orientation))
        if np.all(np.isfinite(v)):
            times.append(_stamp(msg, t_ns))
            values.append(v)
    if not times:
        raise BagError(f"topic '{topic}' has no usable odometry message")
    order = np.argsort(times, kind="stable")
    t, vals = np.asarray(times)[order], np.asarray(values, float)[order]
    vals[:, 2] = np.unwrap(vals[:, 2])
    return t, vals


def _dataset_meta(dataset_dir: Path) -> dict:
    meta_path = dataset_dir / DATASET_FILE
    if not meta_path.is_file():
        return {}
    try:
        meta = json.loads(meta_path.read_text())
    except json.JSONDecodeError as exc:
        raise BagError(f"{meta_path}: not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise BagError(f"{meta_path}: expected a JSON object")
    return meta


def _write_bytes(path: Path, data: bytes) -> None:
    with path.open("wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())


def _encoded(msg: Any, msgtype: str) -> tuple[bytes, str]:
    """(file bytes, suffix) of an image message."""
    from service.api.errors import ServiceError
    from service.vision.imaging import encode_png, sniff_format
    from service.zenoh.ros2 import raw_image

    if msgtype == "sensor_msgs/msg/CompressedImage":
        data = msg.data.tobytes()
        fmt = sniff_format(data)
        if fmt is None:
            raise BagError(f"a CompressedImage (format '{msg.format}') is neither JPEG nor PNG")
        return data, ".jpg" if fmt == "jpeg" else ".png"
    try:
        return encode_png(raw_image(msg, 1 << 40)), ".png"
    except ServiceError as exc:
        raise BagError(f"an Image message cannot be used: {exc.message}") from None


def convert_bag(bag: str | Path, image_topic: str, out: str | Path,
                gps_topic: str | None = None, pose_topic: str | None = None,
                min_distance: float = 0.0, odom_topic: str | None = None) -> Conversion:
    """Write the round ``out`` (which must not exist) from a rosbag2 recording; with
    ``odom_topic``, its ``odometry.csv`` too."""
    from rosbags.rosbag2 import Reader

    from service.zenoh.ros2 import COMPRESSED_IMAGE, IMAGE, make_typestore

    bag, out = Path(bag), Path(out)
    if (gps_topic is None) == (pose_topic is None):
        raise BagError("name exactly one position topic: --gps-topic (NavSatFix) or "
                       "--pose-topic (Odometry, PoseStamped, PoseWithCovarianceStamped)")
    if not is_bag(bag):
        raise BagError(f"{bag}: not a rosbag2 (a directory with metadata.yaml, or a .mcap / "
                       ".db3 file)")
    if out.exists():
        raise BagError(f"{out} exists already; choose a new round directory")
    if min_distance < 0:
        raise BagError(f"--min-distance must be >= 0, got {min_distance}")
    store = make_typestore()
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = _dataset_meta(out.parent)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        with Reader(bag) as reader:
            pt, pv, geographic = _positions(reader, store, gps_topic or pose_topic or "")
            odom = _odometry(reader, store, odom_topic) if odom_topic else None
            origin = None
            if geographic:  # the dataset's shared frame, else one around the first fix
                o = meta.get("origin")
                origin = (float(o["lat"]), float(o["lon"])) if o else (float(pv[0, 0]),
                                                                      float(pv[0, 1]))
            pxy = LocalFrame(*origin).to_local(pv[:, 0], pv[:, 1]) if origin else pv
            conns = _connections(reader, image_topic, (COMPRESSED_IMAGE, IMAGE))
            names: list[str] = []
            xy: list[np.ndarray] = []
            times: list[float] = []
            outside = subsampled = 0
            travelled = last_kept = 0.0
            prev: np.ndarray | None = None
            for conn, t_ns, raw in reader.messages(connections=conns):
                msg = store.deserialize_cdr(raw, conn.msgtype)
                t = _stamp(msg, t_ns)
                if t < pt[0] or t > pt[-1] or (times and t < times[-1]):
                    outside += 1
                    continue
                p = np.array([np.interp(t, pt, pxy[:, 0]), np.interp(t, pt, pxy[:, 1])])
                if prev is not None:
                    travelled += float(np.linalg.norm(p - prev))
                prev = p
                if names and travelled - last_kept < min_distance:
                    subsampled += 1
                    continue
                last_kept = travelled
                data, suffix = _encoded(msg, conn.msgtype)
                name = f"{len(names):05d}{suffix}"
                _write_bytes(tmp / name, data)
                names.append(name)
                xy.append(p)
                times.append(t)
        if not names:
            raise BagError(f"no image of '{image_topic}' lies within the time span of the "
                           f"positions ({outside} images outside it)")
        xy_arr = np.asarray(xy)
        if origin is not None:
            write_round(tmp, names, LocalFrame(*origin).to_geo(xy_arr), np.asarray(times),
                        geographic=True)
        else:
            write_round(tmp, names, xy_arr, np.asarray(times))
        if odom is not None:
            ot, ov = odom
            write_odometry(tmp, names, np.column_stack(
                [np.interp(times, ot, ov[:, k]) for k in range(3)]))
        if origin is not None and "origin" not in meta:
            meta["origin"] = {"lat": origin[0], "lon": origin[1]}
            write_dataset_meta(out.parent, meta)
        tmp.replace(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    length = float(np.linalg.norm(np.diff(xy_arr, axis=0), axis=1).sum())
    return Conversion(out, len(names), outside, subsampled, geographic, origin, length)
