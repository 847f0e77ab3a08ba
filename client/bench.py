"""Benchmarks that print numbers (never asserted in tests)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

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
    import socket
    import threading

    import uvicorn

    from client.dataset import read_round
    from client.transports import HttpClient, LocalClient, ZenohClient
    from service.http_api import create_app
    from service.sessions import LocalizationService
    from service.settings import Settings
    from service.zenoh_bridge import ZenohBridge

    def free_port() -> int:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            return s.getsockname()[1]

    rnd = read_round(round_dir)
    data = [rnd.image_path(i % len(rnd)).read_bytes() for i in range(frames)]
    port, zport = free_port(), free_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    settings = Settings(maps_dir=maps_dir, host="127.0.0.1", port=port, zenoh_listen=[endpoint],
                        zenoh_multicast_scouting=False)
    service = LocalizationService(settings)
    server = uvicorn.Server(uvicorn.Config(create_app(service, lifespan_hooks=[
        ZenohBridge(service)]), host="127.0.0.1", port=port, log_level="warning"))
    th = threading.Thread(target=server.run, daemon=True)
    th.start()
    while not server.started:
        time.sleep(0.05)
    clients = {"in-process": LocalClient(maps_dir),
               "http": HttpClient(f"http://127.0.0.1:{port}"),
               "zenoh": ZenohClient([endpoint], mode="peer")}
    out = []
    try:
        for name, client in clients.items():
            client.create_session("bench", None, "dpso", None, seed)
            times = []
            for k, frame in enumerate(data):
                t0 = time.perf_counter()
                client.localize("bench", frame, t=float(k))
                times.append(1e3 * (time.perf_counter() - t0))
            client.delete_session("bench")
            warm = np.array(times[10:])  # the first frames pay for global convergence
            out.append(LatencyBench(name, len(warm), float(np.percentile(warm, 50)),
                                    float(np.percentile(warm, 99)), float(warm.mean())))
    finally:
        for client in clients.values():
            client.close()
        server.should_exit = True
        th.join(timeout=20)
    return out
