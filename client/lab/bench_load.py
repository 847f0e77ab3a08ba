"""``swarmloc bench load`` and ``swarmloc bench fuzz``: load, soak, fairness and a long fuzz
run against a real service in its own process (``python -m service``), whose resident memory
is read from /proc. Numbers are printed, never asserted."""

from __future__ import annotations

import contextlib
import importlib.util
import os
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from client.lab.stats import percentile
from client.transports import Client, HttpClient, LocalClient, SwarmlocError, ZenohClient
from service.api.models import Estimate, Odometry, PosePrior

FUZZ_SUITE_S = 35.0  # seconds per unit of scale the fuzz tests take on the 2-core machine


@dataclass
class LoadResult:
    name: str
    robots: int
    frames: int
    errors: int
    p50_ms: float
    p99_ms: float
    frames_per_s: float
    rss_mib: float
    error_samples: list[str] = field(default_factory=list)
    cpu_pct: float = float("nan")  # the service's CPU time / wall time during the run (%)
    drops: int = 0  # Zenoh frames replaced by a newer one (swarmloc_zenoh_dropped_frames_total)

    def line(self) -> str:
        return (f"{self.name:<22} robots={self.robots:<3} frames={self.frames:<6} "
                f"errors={self.errors:<3} drops={self.drops:<3} p50={self.p50_ms:7.1f} ms  "
                f"p99={self.p99_ms:7.1f} ms  {self.frames_per_s:6.1f} frames/s  "
                f"cpu={self.cpu_pct:5.0f} %  {self.frames_per_cpu_s:5.1f} frames/CPU-s  "
                f"rss={self.rss_mib:6.1f} MiB")

    @property
    def frames_per_cpu_s(self) -> float:
        """Frames per second of the service's CPU time: what a frame costs it, whatever share
        of the shared cores it got during the run."""
        return 100 * self.frames_per_s / self.cpu_pct if self.cpu_pct > 0 else float("nan")


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux /proc, all its threads)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _dropped(url: str | None) -> int:
    """The service's count of dropped Zenoh frames (0 without a server)."""
    if url is None:
        return 0
    with contextlib.suppress(httpx.HTTPError):
        for line in httpx.get(url + "/metrics", timeout=10).text.splitlines():
            if line.startswith("swarmloc_zenoh_dropped_frames_total "):
                return int(float(line.split()[1]))
    return 0


def _free_port() -> int:
    from service.server import free_port

    return free_port()


def rss_mib(pid: int) -> float:
    """Resident memory of a process (Linux /proc)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


@contextlib.contextmanager
def service_process(maps_dir: Path, **env: str) -> Iterator[tuple[str, str, int]]:
    """``swarmloc serve`` on loopback; yields (http url, zenoh endpoint, pid)."""
    from client.lab.processes import ServiceProcess
    from service.engine.sqlite_store import sqlite_url

    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    with tempfile.TemporaryDirectory() as logs:
        svc = ServiceProcess("bench-load", {
            "SWARMLOC_MAPS_DIR": str(maps_dir), "SWARMLOC_ZENOH_LISTEN": f'["{endpoint}"]',
            "SWARMLOC_SESSION_IDLE_S": "3600",  # the durable default store, in a file of its own
            "SWARMLOC_SESSION_STORE": sqlite_url(Path(logs) / "sessions.sqlite"), **env},
            Path(logs))
        try:
            svc.start().wait_ready(120.0)
            assert svc.proc is not None
            yield svc.url, endpoint, svc.proc.pid
        finally:
            svc.stop()


def _robot_loop(client: Client, robot: str, frames: list[bytes], n: int, start: int,
                times: list[float], errors: list[str], params: dict | None = None) -> None:
    try:
        client.create_session(robot, None, "dpso", params, 0)
    except SwarmlocError as exc:
        errors.append(f"{robot} create: {exc}")
        return
    for k in range(n):
        t0 = time.perf_counter()
        try:
            client.localize(robot, frames[(start + k) % len(frames)], t=float(k))
        except SwarmlocError as exc:
            errors.append(f"{robot} frame {k}: {exc}")
            continue
        times.append(1e3 * (time.perf_counter() - t0))


def _run_robots(name: str, make: Callable[[], Client], robots: int, frames: list[bytes],
                per_robot: int, pid: int, prefix: str,
                clients: list[Client] | None = None, url: str | None = None) -> LoadResult:
    """``robots`` threads, each a robot with its own session; with ``clients`` the robots
    use those connections (kept open by the caller), else a few new ones. ``pid`` is the
    service's process (its CPU time and memory are read), ``url`` its HTTP address (for the
    dropped-frame count)."""
    times: list[float] = []
    errors: list[str] = []
    own = clients is None
    clients = clients or [make() for _ in range(min(robots, 8))]  # shared connections
    threads = [threading.Thread(target=_robot_loop, args=(
        clients[i % len(clients)], f"{prefix}{i}", frames, per_robot, 7 * i, times, errors))
        for i in range(robots)]
    drops0, cpu0 = _dropped(url), cpu_s(pid)
    t0 = time.perf_counter()
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    wall = time.perf_counter() - t0
    cpu = 100 * (cpu_s(pid) - cpu0) / wall
    drops = _dropped(url) - drops0
    for i in range(robots):
        with contextlib.suppress(SwarmlocError):
            clients[i % len(clients)].delete_session(f"{prefix}{i}")
    if own:
        for c in clients:
            c.close()
    arr = np.array(times) if times else np.array([np.nan])
    return LoadResult(name, robots, len(times), len(errors), percentile(arr, 50),
                      percentile(arr, 99), len(times) / wall, rss_mib(pid),
                      errors[:3], cpu, drops)


def _frames(round_dir: Path, limit: int = 60) -> list[bytes]:
    from client.dataset import read_round

    rnd = read_round(round_dir)
    return [rnd.image_path(i).read_bytes() for i in range(min(limit, len(rnd)))]


class _PooledLocal(LocalClient):
    """The service's own ``process_frame`` in this process, run by a pool of ``workers``
    threads in arrival order (as the HTTP route's limiter and the Zenoh bridge's pool do)."""

    def __init__(self, service: Any, pool: ThreadPoolExecutor) -> None:
        super().__init__(service=service)
        self._pool = pool

    def localize(self, robot_id: str, image: np.ndarray | bytes, t: float | None = None,
                 seq: int | None = None, prior: PosePrior | None = None,
                 odom: Odometry | None = None) -> Estimate:
        parent = super().localize
        return self._pool.submit(parent, robot_id, image, t, seq, prior, odom).result()


@contextlib.contextmanager
def local_service(maps_dir: Path) -> Iterator[Callable[[], Client]]:
    """The in-process baseline: a ``LocalizationService`` in this process, set up as
    ``swarmloc serve`` sets up its own (native thread limits, matcher warmed up)."""
    from service.engine.localization_service import LocalizationService
    from service.engine.sqlite_store import sqlite_url
    from service.server import limit_native_threads
    from service.settings import Settings
    from service.vision.matcher import warm_up

    with tempfile.TemporaryDirectory() as tmp:  # the default store, as the service process's
        settings = Settings(maps_dir=maps_dir, zenoh_enabled=False, session_idle_s=3600,
                            session_store=sqlite_url(Path(tmp) / "sessions.sqlite"))
        limit_native_threads(settings)
        warm_up()
        service = LocalizationService(settings)
        try:
            with ThreadPoolExecutor(settings.frame_workers,
                                    thread_name_prefix="local-frames") as pool:
                yield lambda: _PooledLocal(service, pool)
        finally:
            service.close()


def bench_load(maps_dir: Path, round_dir: Path, robots: list[int], per_robot: int,
               transports: list[str], emit: Callable[[str], None] = print) -> list[LoadResult]:
    """p50/p99, errors, drops, throughput, the service's CPU and RSS for each robot count
    and transport (``http``, ``zenoh``: a service in its own process; ``local``: the same
    frames through ``process_frame`` in this process, no transport; its CPU and RSS are this
    process's). With ``local`` among them, each transport's frames/s is also given as a
    ratio to the local frames/s of the same robot count (measured next to it)."""
    frames = _frames(round_dir)
    out = []
    remote = [t for t in transports if t != "local"]
    with contextlib.ExitStack() as stack:
        url = endpoint = None
        pid = os.getpid()
        if remote:
            url, endpoint, pid = stack.enter_context(service_process(maps_dir))
            emit(f"service pid {pid}, rss at start {rss_mib(pid):.1f} MiB")
        local = stack.enter_context(local_service(maps_dir)) if "local" in transports else None
        for n in robots:
            fps: dict[str, float] = {}
            per_cpu: dict[str, float] = {}
            for transport in transports:
                def make(t: str = transport) -> Client:
                    if t == "http":
                        return HttpClient(str(url), timeout=300)
                    return ZenohClient([str(endpoint)], mode="peer", timeout=300)

                if transport == "local":
                    assert local is not None
                    res = _run_robots("local", local, n, frames, per_robot, os.getpid(),
                                      f"local-{n}-")
                else:
                    res = _run_robots(f"{transport}", make, n, frames, per_robot, pid,
                                      f"{transport}-{n}-", url=url)
                emit(res.line())
                for e in res.error_samples:
                    emit(f"    error: {e}")
                out.append(res)
                fps[transport] = res.frames_per_s
                per_cpu[transport] = res.frames_per_cpu_s
            if "local" in fps:
                for t in remote:
                    emit(f"{n} robots: {t} {fps[t]:.2f} frames/s / local {fps['local']:.2f} "
                         f"frames/s = {fps[t] / fps['local']:.2f} (target >= 0.8); per CPU-s "
                         f"of the service: {per_cpu[t] / per_cpu['local']:.2f}")
    return out


def bench_soak(maps_dir: Path, round_dir: Path, total: int, robots: int,
               emit: Callable[[str], None] = print, samples: int = 10,
               transport: str = "http", reconnect: bool = False) -> list[float]:
    """``total`` frames from ``robots`` robots; the server's RSS after every tenth.
    Sessions are deleted and created again every block, as robots come and go."""
    frames = _frames(round_dir)
    block = max(1, total // samples)
    rss: list[float] = []
    with service_process(maps_dir) as (url, endpoint, pid):
        errors = 0
        lat: list[float] = []

        def make() -> Client:
            if transport == "http":
                return HttpClient(url, timeout=300)
            return ZenohClient([endpoint], mode="peer", timeout=300)

        # robots come and go (new sessions every block); with reconnect their connections
        # too, else the connections stay open as a fleet's would
        kept = None if reconnect else [make() for _ in range(min(robots, 8))]
        for b in range(samples):
            res = _run_robots("soak", make, robots, frames, max(1, block // robots), pid,
                              f"soak{b}-", kept)
            errors += res.errors
            lat.append(res.p99_ms)
            rss.append(res.rss_mib)
            emit(f"soak block {b + 1}/{samples}: {(b + 1) * block} frames, errors={errors}, "
                 f"p50={res.p50_ms:.1f} ms, p99={res.p99_ms:.1f} ms, rss={res.rss_mib:.1f} MiB")
        warm = rss[1:] or rss
        growth = (warm[-1] - warm[0]) / warm[0] * 100
        for c in kept or []:
            c.close()
        emit(f"soak ({transport}{', reconnecting' if reconnect else ''}): {total} frames, "
             f"errors={errors}; rss after warm-up "
             f"{warm[0]:.1f} MiB, at the end {warm[-1]:.1f} MiB ({growth:+.1f} %), "
             f"max {max(warm):.1f} MiB")
    return rss


def bench_fairness(maps_dir: Path, round_dir: Path, heavy: int, heavy_particles: int,
                   per_robot: int, emit: Callable[[str], None] = print) -> tuple[float, float]:
    """A light robot's p99 alone, then beside ``heavy`` sessions with ``heavy_particles``."""
    frames = _frames(round_dir)
    with service_process(maps_dir) as (url, _, pid):
        alone = _run_robots("light alone", lambda: HttpClient(url, timeout=300), 1, frames,
                            per_robot, pid, "alone-")
        emit(alone.line())
        stop = threading.Event()
        heavy_errors: list[str] = []

        def heavy_loop(i: int) -> None:
            c = HttpClient(url, timeout=300)
            rid = f"heavy{i}"
            try:
                c.create_session(rid, None, "dpso", {"n_particles": heavy_particles}, i)
                k = 0
                while not stop.is_set():
                    c.localize(rid, frames[k % len(frames)], t=float(k))
                    k += 1
            except SwarmlocError as exc:
                heavy_errors.append(str(exc))
            finally:
                c.close()

        threads = [threading.Thread(target=heavy_loop, args=(i,)) for i in range(heavy)]
        for th in threads:
            th.start()
        time.sleep(2.0)  # the heavy sessions are running
        loaded = _run_robots(f"light + {heavy} heavy", lambda: HttpClient(url, timeout=300),
                             1, frames, per_robot, pid, "loaded-")
        stop.set()
        for th in threads:
            th.join()
        emit(loaded.line())
        emit(f"fairness: light p99 {loaded.p99_ms:.1f} ms beside {heavy} sessions of "
             f"{heavy_particles} particles vs {alone.p99_ms:.1f} ms alone = "
             f"{loaded.p99_ms / alone.p99_ms:.2f}x (heavy errors: {len(heavy_errors)})")
    return alone.p99_ms, loaded.p99_ms


def fuzz_test_files() -> list[Path]:
    """The suite's fuzz test files in this source checkout (tests/ at its top level)."""
    tests = Path(__file__).resolve().parents[2] / "tests"
    return [tests / "test_fuzz_parsers.py", tests / "test_schemathesis.py"]


def bench_fuzz(minutes: float, seed: int | None = None,
               emit: Callable[[str], None] = print) -> int:
    """The suite's fuzz tests (hypothesis parsers + schemathesis), for ``minutes`` in all,
    with many more examples; returns pytest's exit code."""
    import pytest

    files = fuzz_test_files()
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        emit(f"the fuzz tests are not here ({missing}): run from a source checkout")
        return 2
    # the suite's examples take about FUZZ_SUITE_S; scale them to the wanted minutes
    os.environ["SWARMLOC_FUZZ_SCALE"] = f"{max(1.0, 60.0 * minutes / FUZZ_SUITE_S):.2f}"
    args = ["-q", "-x", "-p", "no:cacheprovider", *map(str, files)]
    if importlib.util.find_spec("xdist") is not None:
        args += ["-n", "0"]  # one process (the project's addopts ask for a worker per core)
    if seed is not None:
        args.append(f"--hypothesis-seed={seed}")
    t0 = time.perf_counter()
    code = int(pytest.main(args))
    emit(f"fuzz: {time.perf_counter() - t0:.0f} s, exit code {code} "
         f"({'no failures' if code == 0 else 'FAILURES, see above'})")
    return code
