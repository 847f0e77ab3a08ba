"""``swarmloc bench scale``: what the Redis session store costs per frame, and the frames per
second of one and two replicas (real ``swarmloc serve`` processes on one real redis-server)."""

from __future__ import annotations

import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import httpx

from client.lab.stats import percentile

if TYPE_CHECKING:
    from service.engine.localization_service import LocalizationService


@dataclass(frozen=True)
class StoreOverhead:
    store: str
    frames: int
    load_p50_ms: float  # session lookup + lock + load (+ decode when another replica wrote)
    load_p99_ms: float
    store_p50_ms: float  # encode + compare-and-set write + unlock
    store_p99_ms: float
    step_p50_ms: float  # the estimator step itself, for scale
    state_bytes: int
    with_step: bool  # False: load and store back to back, no estimator step between


@dataclass(frozen=True)
class Throughput:
    setup: str
    replicas: int
    robots: int
    frames: int
    seconds: float

    @property
    def fps(self) -> float:
        return self.frames / self.seconds


def timed_frame(svc: LocalizationService, robot: str, features: Any, k: int,
                step: bool = True) -> tuple[float, float, float]:
    """Frame ``k`` of ``robot`` through the store as ``process_frame`` takes it (look-up,
    lock and load, the estimator step, store back and unlock): (load, step, store) seconds."""
    t0 = time.perf_counter()
    svc.session(robot)  # what a transport does first (404 for an unknown robot)
    cm = svc.store.locked(robot)
    s = cm.__enter__()
    t1 = time.perf_counter()
    if step:
        s.localizer.step(features, float(k))
    s.last_t, s.last_used = float(k), time.time()
    t2 = time.perf_counter()
    cm.__exit__(None, None, None)
    return t1 - t0, t2 - t1, time.perf_counter() - t2


def bench_store_overhead(maps_dir: str, round_dir: str, redis_url: str, frames: int = 200,
                         estimator: str = "dpso", seed: int = 0) -> list[StoreOverhead]:
    """Per-frame cost of the store around the estimator step, for the in-process store, Redis
    with a robot that stays on one replica (its state is cached: no decoding), and Redis with
    frames alternating between two replicas (every load decodes the other one's state)."""
    from client.dataset import read_round
    from service.api.models import EstimatorName, SessionConfig
    from service.engine.localization_service import LocalizationService
    from service.engine.state_codec import encode_session
    from service.settings import Settings

    rnd = read_round(round_dir)
    mem = LocalizationService(Settings(maps_dir=Path(maps_dir), zenoh_enabled=False,
                                       session_store="memory"))
    maps = mem.maps
    a, b = (LocalizationService(Settings(maps_dir=Path(maps_dir), zenoh_enabled=False,
                                         session_store=redis_url, replica_id=n), maps=maps)
            for n in ("bench-a", "bench-b"))
    cfg = SessionConfig(estimator=cast(EstimatorName, estimator), seed=seed)
    mem.put_session("probe", cfg)
    loc = mem.session("probe").localizer
    feats = [loc.extract(rnd.load_image(i % len(rnd))) for i in range(min(frames, len(rnd)))]
    out = []
    for with_step in (True, False):
        for name, replicas in (("in-process", (mem,)), ("redis, one replica", (a,)),
                               ("redis, alternating replicas", (a, b))):
            robot = f"bench-{with_step:d}-" + name.replace(" ", "").replace(",", "-")
            replicas[0].put_session(robot, cfg)
            load, store, step = [], [], []
            size = 0
            for k in range(frames):
                svc = replicas[k % len(replicas)]
                times = timed_frame(svc, robot, feats[k % len(feats)], k, with_step or k < 5)
                load.append(times[0])
                step.append(times[1])
                store.append(times[2])
            size = len(encode_session(replicas[0].session(robot)))
            ms = [(percentile(x, 50, 1e3), percentile(x, 99, 1e3)) for x in (load, store, step)]
            out.append(StoreOverhead(name, frames, *ms[0], *ms[1], ms[2][0], size, with_step))
    return out


def _drive(urls: list[str], robots: int, data: list[bytes], per_robot: int,
           tag: str) -> float:
    """``robots`` robots in parallel, each sending ``per_robot`` frames one after another,
    frame k of robot i to replica (i + k) mod n; the wall time of it all."""
    errors: list[str] = []

    def robot(i: int) -> None:
        rid = f"{tag}-{i}"
        with httpx.Client(timeout=120) as c:
            r = c.put(f"{urls[i % len(urls)]}/sessions/{rid}", json={"seed": i})
            if r.status_code not in (200, 201):
                errors.append(r.text)
                return
            for k in range(per_robot):
                r = c.post(f"{urls[(i + k) % len(urls)]}/sessions/{rid}/frames",
                           params={"t": float(k), "seq": k}, content=data[(i + k) % len(data)],
                           headers={"Content-Type": "image/png"})
                if r.status_code != 200:
                    errors.append(r.text)
                    return

    threads = [threading.Thread(target=robot, args=(i,)) for i in range(robots)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    seconds = time.perf_counter() - t0
    if errors:
        raise RuntimeError(f"frames failed: {errors[:3]}")
    return seconds


def bench_replicas(maps_dir: str, round_dir: str, redis_url: str, robots: int = 4,
                   per_robot: int = 30) -> list[Throughput]:
    """Frames per second over HTTP: one replica with the in-process store, one and two
    replicas on Redis (real processes, ``robots`` robots sending in parallel)."""
    from client.dataset import read_round
    from client.lab.processes import ServiceProcess

    rnd = read_round(round_dir)
    data = [rnd.image_path(i).read_bytes() for i in range(min(len(rnd), 60))]
    env = {"SWARMLOC_MAPS_DIR": str(maps_dir), "SWARMLOC_ZENOH_ENABLED": "false"}
    out = []
    with tempfile.TemporaryDirectory() as logs:
        for setup, n, store in (("in-process store", 1, "memory"), ("redis store", 1, redis_url),
                                ("redis store", 2, redis_url)):
            procs = [ServiceProcess(f"bench-{n}-{i}", {**env, "SWARMLOC_SESSION_STORE": store},
                                    Path(logs)).start() for i in range(n)]
            try:
                for p in procs:
                    p.wait_ready()
                urls = [p.url for p in procs]
                _drive(urls, 1, data, 3, f"warm{n}{store[:1]}")  # first frames: JIT, caches
                seconds = _drive(urls, robots, data, per_robot, f"run{n}{store[:1]}")
                out.append(Throughput(setup, n, robots, robots * per_robot, seconds))
            finally:
                for p in procs:
                    p.stop()
    return out


def with_redis(url: str | None) -> tuple[str, object | None]:
    """``url``, or a fresh redis-server on a free loopback port (returned to be stopped)."""
    if url:
        return url, None
    from client.lab.processes import RedisServer

    srv = RedisServer(Path(tempfile.mkdtemp(prefix="swarmloc-redis-"))).start()
    return srv.url, srv
