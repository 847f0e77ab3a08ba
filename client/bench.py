"""Benchmarks that print numbers (never asserted in tests)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from client.transports import Client
from client.world import Pose, World
from service.features import extract, match_batch, similarity_bfmatcher
from service.route_map import prune


def _median_ms(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


@dataclass
class SimilarityBench:
    extract_ms: float
    batched_ms_per_comparison: float
    bfmatcher_ms_per_comparison: float
    speedup: float
    k: int
    frame_features: float
    map_features: float
    counts_equal: bool


def bench_similarity(seed: int = 0, k: int = 20, repeats: int = 7) -> SimilarityBench:
    """SIFT extraction per 320x240 frame; batched m(A, B) vs BFMatcher on the same descriptors.

    Frames come from a rendered round; the K map-side sets are pruned like a real map.
    """
    world = World(seed)
    poses, t, _ = world.round_trajectory(0)
    frames = [world.render(Pose(*poses[i]), "sunny", t=float(t[i]), noise_seed=i)
              for i in range(0, 2 * (k + 2), 2)]
    extract_ms = float(np.median([_median_ms(lambda f=f: extract(f), 1) for f in frames]))
    feats = [extract(f) for f in frames]
    pruned, _ = prune(feats)
    query = extract(world.render(Pose(*poses[1]), "cloudy", t=float(t[1]), noise_seed=99))
    sets = [p.descriptors for p in pruned[:k]]
    a = query.descriptors
    batched = _median_ms(lambda: match_batch(a, sets), repeats) / k
    bf = _median_ms(lambda: [similarity_bfmatcher(a, b) for b in sets], max(3, repeats // 2)) / k
    counts = match_batch(a, sets).counts.tolist()
    ref = [similarity_bfmatcher(a, b)[0] for b in sets]
    return SimilarityBench(extract_ms, batched, bf, bf / batched, k, float(len(a)),
                           float(np.mean([len(s) for s in sets])), counts == ref)


@dataclass
class LatencyBench:
    transport: str
    frames: int
    p50_ms: float
    p99_ms: float
    mean_ms: float


def bench_latency(maps_dir: str, round_dir: str, frames: int = 200, seed: int = 0
                  ) -> list[LatencyBench]:
    """Per-frame latency as a robot sees it, 320x240 PNG frames, against a real server
    (uvicorn + Zenoh bridge on loopback) and in process (no transport) for reference."""
    from client.dataset import read_round
    from client.transports import HttpClient, LocalClient, ZenohClient
    from service.server import free_port, running_server
    from service.sessions import LocalizationService
    from service.settings import Settings

    rnd = read_round(round_dir)
    data = [rnd.image_path(i % len(rnd)).read_bytes() for i in range(frames)]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = Settings(maps_dir=maps_dir, host="127.0.0.1", port=free_port(),
                        zenoh_listen=[endpoint], zenoh_multicast_scouting=False)
    with running_server(LocalizationService(settings)) as url:
        clients = {"in-process": LocalClient(maps_dir), "http": HttpClient(url),
                   "zenoh": ZenohClient([endpoint], mode="peer")}
        try:
            return [_time_frames(name, c, data, seed) for name, c in clients.items()]
        finally:
            for c in clients.values():
                c.close()


def _time_frames(name: str, client: Client, data: list[bytes], seed: int) -> LatencyBench:
    client.create_session("bench", None, "dpso", None, seed)
    times = []
    for k, frame in enumerate(data):
        t0 = time.perf_counter()
        client.localize("bench", frame, t=float(k))
        times.append(1e3 * (time.perf_counter() - t0))
    client.delete_session("bench")
    warm = np.array(times[10:])  # the first frames pay for global convergence
    return LatencyBench(name, len(warm), float(np.percentile(warm, 50)),
                        float(np.percentile(warm, 99)), float(warm.mean()))


@dataclass
class Ros2Bench:
    jpeg_bytes: int
    compressed_in_ms: float  # CDR CompressedImage -> validated bytes
    image_in_ms: float  # CDR mono8 Image -> grayscale pixels
    bgr_in_ms: float  # CDR bgr8 Image -> grayscale pixels
    pose_out_ms: float  # Estimate -> CDR PoseWithCovarianceStamped
    status_out_ms: float  # Estimate -> CDR DiagnosticStatus
    extract_ms: float  # SIFT on the same frame, for scale


def bench_ros2(seed: int = 0, repeats: int = 200) -> Ros2Bench:
    """What the ROS 2 layer adds per frame: CDR decoding of a 320x240 frame (rosbags) and
    encoding of the answer, beside the frame's SIFT extraction."""
    import cv2

    from service.models import Estimate
    from service.ros2 import COMPRESSED_IMAGE, IMAGE, Codec, Stamp

    codec = Codec()
    t = codec.types
    world = World(seed)
    poses, times, _ = world.round_trajectory(0)
    img = world.render(Pose(*poses[5]), "sunny", t=float(times[5]), noise_seed=5)
    jpeg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].ravel()
    header = t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="camera")
    comp = codec.serialize(t[COMPRESSED_IMAGE](header=header, format="jpeg", data=jpeg),
                           COMPRESSED_IMAGE)
    h, w = img.shape

    def raw(enc: str, pixels: np.ndarray) -> bytes:
        return codec.serialize(t[IMAGE](header=header, height=h, width=w, encoding=enc,
                                        is_bigendian=0, step=pixels.size // h,
                                        data=pixels.ravel()), IMAGE)

    mono, bgr = raw("mono8", img), raw("bgr8", np.dstack([img, img, img]))
    big = 1 << 30
    est = Estimate(seq=1, stamp=1.0, frame_id="map", estimator="dpso", x=1.0, y=2.0,
                   heading=0.5, speed=1.0, status="tracking", lost=False, score=0.2,
                   comparisons=20, covariance=[[1.0, 0.0], [0.0, 1.0]],
                   pose_covariance=[0.0] * 36, accuracy_m=1.5, nearest_image=0,
                   nearest_image_name="00000.png", spread_m=1.0)
    body = est.model_dump(mode="json")
    return Ros2Bench(
        len(jpeg),
        _median_ms(lambda: codec.frame(comp, COMPRESSED_IMAGE, big, big), repeats),
        _median_ms(lambda: codec.frame(mono, IMAGE, big, big), repeats),
        _median_ms(lambda: codec.frame(bgr, IMAGE, big, big), repeats),
        _median_ms(lambda: codec.pose(est, Stamp(1, 0), "map", 0.3), repeats),
        _median_ms(lambda: codec.status("robot1", body), repeats),
        _median_ms(lambda: extract(img), 15))
