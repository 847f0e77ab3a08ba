"""rosbag2 recordings written by rosbags (sqlite3 and MCAP) -> round -> map -> replay."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from typer.testing import CliRunner

from client.cli import app
from client.dataset import Round, read_round, write_dataset_meta
from service.api.geo import LocalFrame

TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types
T0 = 1_700_000_000.0  # first image stamp, s
ORIGIN = (48.5216, 9.0576)  # the truth frame's geodetic origin (Tübingen)
MAP_N = 95  # map images (of the small world's sunny1); the queries stay within them
runner = CliRunner()


def _header(t: float, frame_id: str) -> object:
    sec = int(t)
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=round((t - sec) * 1e9)),
        frame_id=frame_id)


def _point(x: float, y: float) -> object:
    return T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
        orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))


def write_bag(path: Path, storage: StoragePlugin, rnd: Round, images: str, positions: str,
              frames: range) -> np.ndarray:
    """A bag of the round's frames at 1 Hz (``images``: png, jpeg or mono8) and positions at
    2 Hz, a quarter second off the images (``positions``: gps or odom). One image lies before
    the first position; two GPS messages without a fix carry junk. Returns the image times."""
    truth = rnd.reference_xy[list(frames)]
    t_img = T0 + np.arange(len(frames), dtype=float)
    t_pos = np.arange(T0 + 0.75, t_img[-1] + 0.6, 0.5)  # the first image has no position
    pos_xy = np.column_stack([np.interp(t_pos, t_img, truth[:, 0]),
                              np.interp(t_pos, t_img, truth[:, 1])])
    geo = LocalFrame(*ORIGIN).to_geo(pos_xy)
    with Writer(path, version=9, storage_plugin=storage) as w:
        img_type = "sensor_msgs/msg/Image" if images == "mono8" else \
            "sensor_msgs/msg/CompressedImage"
        cam = w.add_connection("/robot1/camera/image_raw" + ("" if images == "mono8"
                                                             else "/compressed"),
                               img_type, typestore=TS)
        pos_type = "sensor_msgs/msg/NavSatFix" if positions == "gps" else "nav_msgs/msg/Odometry"
        pos = w.add_connection("/fix" if positions == "gps" else "/odom", pos_type,
                               typestore=TS)
        msgs: list[tuple[float, object, object]] = []
        for k, i in enumerate(frames):
            img = rnd.load_image(i)
            if images == "mono8":
                m = T[img_type](header=_header(t_img[k], "camera"), height=img.shape[0],
                                width=img.shape[1], encoding="mono8", is_bigendian=0,
                                step=img.shape[1], data=img.ravel())
            else:
                ok, buf = cv2.imencode(".png" if images == "png" else ".jpg", img)
                assert ok
                m = T[img_type](header=_header(t_img[k], "camera"), format=images,
                                data=buf.ravel())
            msgs.append((t_img[k], cam, m))
        for j, t in enumerate(t_pos):
            if positions == "gps":
                status = T["sensor_msgs/msg/NavSatStatus"](status=0, service=1)
                m = T[pos_type](header=_header(t, "gps"), status=status,
                                latitude=geo[j, 0], longitude=geo[j, 1], altitude=300.0,
                                position_covariance=np.zeros(9), position_covariance_type=0)
            else:
                m = T[pos_type](
                    header=_header(t, "odom"), child_frame_id="base_link",
                    pose=T["geometry_msgs/msg/PoseWithCovariance"](
                        pose=_point(*pos_xy[j]), covariance=np.zeros(36)),
                    twist=T["geometry_msgs/msg/TwistWithCovariance"](
                        twist=T["geometry_msgs/msg/Twist"](
                            linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                            angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                        covariance=np.zeros(36)))
            msgs.append((t, pos, m))
        if positions == "gps":  # no fix: must be ignored
            for t in (t_pos[3] + 0.1, t_pos[8] + 0.1):
                m = T[pos_type](header=_header(t, "gps"),
                                status=T["sensor_msgs/msg/NavSatStatus"](status=-1, service=1),
                                latitude=0.0, longitude=0.0, altitude=0.0,
                                position_covariance=np.zeros(9), position_covariance_type=0)
                msgs.append((t, pos, m))
        for t, conn, m in sorted(msgs, key=lambda x: x[0]):
            w.write(conn, round(float(t) * 1e9), TS.serialize_cdr(m, conn.msgtype))
    return t_img


def _cli(*args: object) -> str:
    res = runner.invoke(app, [str(a) for a in args])
    assert res.exit_code == 0, res.output
    return res.output


@pytest.fixture(scope="module")
def bags(tmp_path_factory, sunny1, sunny2) -> dict:
    root = tmp_path_factory.mktemp("bags")
    return {
        "gps_sqlite": (root / "sunny1_gps", write_bag(root / "sunny1_gps", StoragePlugin.SQLITE3,
                                                      sunny1, "png", "gps", range(MAP_N))),
        "odom_mcap": (root / "sunny2_odom", write_bag(root / "sunny2_odom", StoragePlugin.MCAP,
                                                      sunny2, "mono8", "odom", range(0, 45))),
        "gps_mcap": (root / "sunny2_gps", write_bag(root / "sunny2_gps", StoragePlugin.MCAP,
                                                    sunny2, "jpeg", "gps", range(40, 85))),
    }


def test_bag_to_map_to_replay(tmp_path: Path, bags, sunny1, sunny2) -> None:
    data = tmp_path / "data"
    write_dataset_meta(data, {"name": "bags", "origin": {"lat": ORIGIN[0], "lon": ORIGIN[1]}})
    bag, t_img = bags["gps_sqlite"]
    assert (bag / "metadata.yaml").is_file() and list(bag.glob("*.db3"))
    out = _cli("dataset", "from-bag", bag, "--image-topic", "/robot1/camera/image_raw/compressed",
               "--gps-topic", "/fix", "--out", data / "sunny1")
    assert f"{MAP_N - 1} images" in out and "left out 1 outside" in out
    rnd = read_round(data / "sunny1")
    assert len(rnd) == MAP_N - 1 and rnd.origin == ORIGIN
    err = np.linalg.norm(rnd.xy - sunny1.reference_xy[1:MAP_N], axis=1)
    assert err.max() < 0.1  # interpolated to the image stamps, no-fix messages ignored
    assert err[:-1].max() < 0.05  # (the last image: the truth ends there, the test clamps it)
    assert np.allclose(rnd.t, t_img[1:], atol=1e-3)
    assert rnd.image_path(0).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert np.array_equal(rnd.load_image(5), sunny1.load_image(6))  # PNG kept as recorded
    maps = tmp_path / "maps"
    _cli("map", "build", data / "sunny1", "--out", maps / "bagmap")

    # an MCAP bag with raw mono8 images and odometry (in the map's metric frame), replayed
    # directly: converted on the fly
    bag, _ = bags["odom_mcap"]
    assert list(bag.glob("*.mcap"))
    out = _cli("replay", bag, "--image-topic", "/robot1/camera/image_raw", "--pose-topic",
               "/odom", "--map", "bagmap", "--via", f"local:{maps}", "--out",
               tmp_path / "report_odom", "--seed", 2)
    report = json.loads((tmp_path / "report_odom" / "report.json").read_text())
    s = report["summary"]
    assert report["runs"][0]["metrics"]["frames"] == 44
    assert s["error_mean_m"] < 3.0 and s["within_5m"] > 0.8, s
    assert "mean error" in out

    # an MCAP bag with JPEG images and GPS: projected in the map's frame (its origin)
    bag, _ = bags["gps_mcap"]
    _cli("replay", bag, "--image-topic", "/robot1/camera/image_raw/compressed",
         "--gps-topic", "/fix", "--map", "bagmap", "--via", f"local:{maps}", "--out",
         tmp_path / "report_gps", "--seed", 2)
    s = json.loads((tmp_path / "report_gps" / "report.json").read_text())["summary"]
    assert s["error_mean_m"] < 3.0 and s["within_5m"] > 0.8, s


def test_subsampling_by_distance_and_a_new_dataset_origin(tmp_path: Path, bags,
                                                          sunny2) -> None:
    bag, _ = bags["gps_mcap"]
    data = tmp_path / "fresh"
    mcap = bag / f"{bag.name}.mcap"  # the storage file alone, without metadata.yaml
    assert mcap.is_file()
    _cli("dataset", "from-bag", mcap, "--image-topic", "/robot1/camera/image_raw/compressed",
         "--gps-topic", "/fix", "--out", data / "r", "--min-distance", 1.5)
    meta = json.loads((data / "dataset.json").read_text())
    rnd = read_round(data / "r")
    first_fix = LocalFrame(*ORIGIN).to_geo(sunny2.reference_xy[41])[0]
    assert abs(meta["origin"]["lat"] - rnd.origin[0]) < 1e-12
    assert np.linalg.norm(rnd.xy[0]) < 0.7  # the frame is centred on the first fix
    assert abs(meta["origin"]["lat"] - first_fix[0]) < 1e-5
    steps = np.linalg.norm(np.diff(rnd.xy, axis=0), axis=1)
    spacing = float(np.median(np.linalg.norm(np.diff(sunny2.reference_xy, axis=0), axis=1)))
    assert steps.min() > 1.5 - 0.05 and steps.max() < 1.5 + 1.5 * spacing
    assert 0.25 * 44 < len(rnd) < 0.55 * 44


def test_the_odometry_topic_fills_odometry_csv(tmp_path: Path, bags) -> None:
    bag, _ = bags["odom_mcap"]
    _cli("dataset", "from-bag", bag, "--image-topic", "/robot1/camera/image_raw",
         "--pose-topic", "/odom", "--odom-topic", "/odom", "--out", tmp_path / "r")
    rnd = read_round(tmp_path / "r")
    assert rnd.odometry is not None and rnd.odometry.shape == (len(rnd), 3)
    assert np.allclose(rnd.odometry[:, :2], rnd.xy, atol=1e-3)  # the same topic, same stamps
    assert np.allclose(rnd.odometry[:, 2], 0.0)  # the bag's orientation is the identity


def test_bag_errors_say_what_is_wrong(tmp_path: Path, bags) -> None:
    bag, _ = bags["odom_mcap"]
    cases = [
        (["--image-topic", "/nope", "--pose-topic", "/odom"], "'/nope' is not in the bag"),
        (["--image-topic", "/robot1/camera/image_raw", "--pose-topic", "/odom",
          "--gps-topic", "/fix"], "exactly one position topic"),
        (["--image-topic", "/robot1/camera/image_raw", "--gps-topic",
          "/robot1/camera/image_raw"], "has type sensor_msgs/msg/Image"),
        (["--image-topic", "/odom", "--pose-topic", "/odom"], "expected sensor_msgs"),
    ]
    for k, (args, words) in enumerate(cases):
        res = runner.invoke(app, ["dataset", "from-bag", str(bag), *args, "--out",
                                  str(tmp_path / f"r{k}")])
        assert res.exit_code == 2 and words in res.output, res.output
        assert not (tmp_path / f"r{k}").exists()
    assert list(tmp_path.iterdir()) == []  # nothing half-written
    res = runner.invoke(app, ["dataset", "from-bag", str(tmp_path), "--image-topic", "/x",
                              "--pose-topic", "/odom", "--out", str(tmp_path / "r")])
    assert res.exit_code == 2 and "not a rosbag2" in res.output
