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


def bench_build_latency(maps_dir: str, round_dir: str, frames: int = 150, fps: float = 5.0,
                        seed: int = 0, duty: float = 0.5
                        ) -> tuple[list[LatencyBench], float, str]:
    """Frame latency of one robot streaming over HTTP at ``fps``: with no build, then while
    the service builds a map from ``round_dir``, then with no build again (real server; the
    maps are copied to a temporary folder). Returns the three latencies, the build's duration
    (s) and its final state."""
    import shutil
    import tempfile
    from pathlib import Path

    from client.dataset import read_round
    from client.map_remote import zip_round
    from client.transports import HttpClient
    from service.server import free_port, running_server
    from service.sessions import LocalizationService
    from service.settings import Settings

    rnd = read_round(round_dir)
    data = [rnd.image_path(i).read_bytes() for i in range(len(rnd))]
    period = 1.0 / fps if fps > 0 else 0.0
    with tempfile.TemporaryDirectory() as tmp:
        maps = Path(tmp) / "maps"
        maps.mkdir()
        for f in Path(maps_dir).glob("*.swmap"):
            shutil.copy(f, maps / f.name)
        archive = zip_round(round_dir, Path(tmp) / "round.zip")
        settings = Settings(maps_dir=maps, host="127.0.0.1", port=free_port(),
                            zenoh_enabled=False, build_duty=duty)
        with running_server(LocalizationService(settings), zenoh=False) as url:
            client = HttpClient(url)
            try:
                client.create_session("bench", None, "dpso", None, seed)
                k = 0

                def frame() -> float:
                    nonlocal k
                    t0 = time.perf_counter()
                    client.localize("bench", data[k % len(data)], t=float(k))
                    k += 1
                    took = time.perf_counter() - t0
                    time.sleep(max(0.0, period - took))
                    return 1e3 * took

                idle = [frame() for _ in range(frames)][10:]  # after global convergence
                job = client.build_map_remote("bench-build", archive)
                busy, polled = [], time.monotonic()
                while job.state in ("queued", "running"):
                    busy.append(frame())
                    if time.monotonic() - polled > 1.0:
                        job, polled = client.job(job.id), time.monotonic()
                job = client.job(job.id)
                build_s = (job.finished or 0.0) - (job.started or 0.0)
                after = [frame() for _ in range(frames - 10)]  # brackets drifting load
            finally:
                client.close()
    return ([_stats("no build", idle), _stats("during build", busy),
             _stats("no build, after", after)], build_s, job.state)


def _stats(name: str, times: list[float]) -> LatencyBench:
    a = np.array(times)
    return LatencyBench(name, len(a), float(np.percentile(a, 50)), float(np.percentile(a, 99)),
                        float(a.mean()))
