"""Assemble and run the service: maps, engine, HTTP app, Zenoh bridge, uvicorn."""

from __future__ import annotations

import contextlib
import logging
import math
import os
import random
import socket
import threading
import time
from collections.abc import Iterator

import uvicorn
from fastapi import FastAPI

from service.engine.localization_service import LocalizationService
from service.http.app import create_app
from service.http.limits import limited_protocol
from service.settings import Settings
from service.zenoh.bridge import ZenohBridge
from service.zenoh.config import check_security

log = logging.getLogger("swarmloc")


class _Server(uvicorn.Server):
    """uvicorn with a bounded, draining shutdown: new frames get 503 at once, frames in
    flight get ``shutdown_deadline_s`` (uvicorn's graceful timeout) and the open event
    streams (GET /events) are ended, since they never end by themselves."""

    def __init__(self, config: uvicorn.Config, service: LocalizationService) -> None:
        super().__init__(config)
        self._service = service

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        self._service.begin_shutdown()
        self._service.events.close()
        await super().shutdown(sockets)
        # frames have stopped: the in-process store writes its snapshot (if configured);
        # here, not after run(): uvicorn re-raises SIGTERM when it returns
        self._service.close()


def _uvicorn_config(app: FastAPI, settings: Settings, log_level: str) -> uvicorn.Config:
    return uvicorn.Config(app, host=settings.host, port=settings.port, log_level=log_level,
                          timeout_graceful_shutdown=math.ceil(settings.shutdown_deadline_s),
                          http=limited_protocol(settings.http_max_header_bytes,
                                                settings.http_read_timeout_s))


def build_app(settings: Settings) -> FastAPI:
    if settings.zenoh_enabled:
        check_security(settings)  # refuse before loading maps, with the reason
    service = LocalizationService(settings)
    hooks = [ZenohBridge(service)] if settings.zenoh_enabled else []
    return create_app(service, lifespan_hooks=hooks)


def limit_native_threads(settings: Settings) -> None:
    """Robots run in parallel threads: one BLAS thread each and ``opencv_threads`` OpenCV
    threads, not pools of threads per call fighting over the cores (OpenCV's idle workers
    spin after each parallel call and delay the threads that answer the robots). Process-wide;
    features and estimates do not depend on it."""
    import cv2
    from threadpoolctl import threadpool_limits

    threadpool_limits(1, "blas")
    if settings.opencv_threads:
        cv2.setNumThreads(settings.opencv_threads)


def run(settings: Settings) -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    if settings.zenoh_enabled:
        check_security(settings)  # before the kernels compile: the refusal comes at once
    limit_native_threads(settings)
    app = build_app(settings)
    service: LocalizationService = app.state.service
    kernels = warm_kernels(settings, service)
    print(startup_banner(settings, sorted(service.maps), service.load_errors, kernels),
          flush=True)
    _Server(_uvicorn_config(app, settings, "info"), service).run()


def warm_kernels(settings: Settings, service: LocalizationService) -> str:
    """Compile (or load from the cache directory) the matcher's kernels and run each loaded
    map's feature type once, before the service reports ready: the first frame then costs
    what a later one does. Returns the banner's line on where the kernels are cached."""
    import numpy as np

    from service.vision.features import extract
    from service.vision.matcher import cache_kernels_in, default_cache_dir, fastest_gemm, warm_up
    from service.vision.mnn_matcher import warm_up as warm_up_mnn

    wanted = settings.numba_cache_dir or default_cache_dir()
    used = cache_kernels_in(wanted)
    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    for p in dict.fromkeys(m.feature_params for m in service.maps.values()):
        extract(rng.integers(0, 256, (p.height, p.width), dtype=np.uint8), p)  # XFeat: ONNX
    gemm = fastest_gemm()  # measured now, not on the first frame
    gemm_xfeat = fastest_gemm("int8")
    warm_up()
    warm_up_mnn()
    took = (f"ready in {time.perf_counter() - t0:.1f} s, exact GEMM {gemm.describe()}, "
            f"XFeat's {gemm_xfeat.describe()}")
    if used is None:
        return (f"{took}, compiled at each start: {wanted} is not writable "
                "(SWARMLOC_NUMBA_CACHE_DIR)")
    return f"{took}, cached in {used}"


def startup_banner(settings: Settings, maps: list[str], load_errors: dict[str, str],
                   kernels: str | None = None) -> str:
    """What a new operator needs at start-up: where to point a robot, a browser and a Zenoh
    peer, and whether the service is open to anyone who reaches it."""
    from service import __version__

    url = public_url(settings.host, settings.port)
    wildcard = settings.host in ("0.0.0.0", "::", "")
    auth = bool(settings.auth_token)
    if settings.zenoh_enabled:
        ends = [f"listen {e}" for e in settings.zenoh_listen] + \
            [f"connect {e}" for e in settings.zenoh_connect]
        zenoh = f"{', '.join(ends) or 'no endpoints'} (mode {settings.zenoh_mode}, prefix " \
                f"'{settings.zenoh_prefix}')"
    else:
        zenoh = "off"
    ros2 = f"on ({settings.ros2_key_format} keys)" if settings.zenoh_enabled and \
        settings.ros2_enabled else "off"
    loaded = f"{len(maps)} from {settings.maps_dir}/: {', '.join(maps)}" if maps else \
        f"none in {settings.maps_dir}/ (GET /readyz answers 503 until one is uploaded)"
    if load_errors:
        loaded += f"; {len(load_errors)} refused: {', '.join(sorted(load_errors))}"
    if settings.maps_sync == "redis":
        loaded += "; shared with the other replicas through Redis"
    rows = [
        ("HTTP", url + ("  (all interfaces)" if wildcard else "") + "  API docs: " +
         f"{url}/docs"),
        ("viewer", f"{url}/viewer" + ("?token=<SWARMLOC_AUTH_TOKEN>" if auth else "")),
        ("Zenoh", zenoh),
        ("ROS 2", ros2),
        ("auth", "on: bearer token" if auth else
         "off: anyone who reaches the port can use the API (--token)"),
        ("maps", loaded),
        ("sessions", session_store_name(settings)),
    ]
    if kernels is not None:
        rows.append(("kernels", kernels))
    width = max(len(k) for k, _ in rows)
    return "\n".join([f"swarmloc {__version__}"] +
                     [f"  {k:<{width}}  {v}" for k, v in rows])


def public_url(host: str, port: int) -> str:
    """The URL to open for a bind address (a wildcard address: this machine's loopback)."""
    if host in ("0.0.0.0", ""):
        host = "127.0.0.1"
    elif host == "::":
        host = "[::1]"
    elif ":" in host:
        host = f"[{host}]"
    return f"http://{host}:{port}"


def session_store_name(settings: Settings) -> str:
    """The session store, without a password in its URL."""
    store = settings.session_store
    if store == "memory":
        snap = settings.session_snapshot
        return "in-process" + (f", snapshot {snap}" if snap else " (lost on restart)")
    if store == "sqlite" or store.startswith("sqlite:"):
        from service.engine.sqlite_store import sqlite_location

        path, _ = sqlite_location(store, settings.maps_dir)
        return f"SQLite {path} (durable)"
    from urllib.parse import urlsplit

    parts = urlsplit(store)
    if parts.password:
        netloc = f"{parts.username or ''}:***@{parts.hostname}" + \
            (f":{parts.port}" if parts.port else "")
        store = parts._replace(netloc=netloc).geturl()
    return store


# Ports for the servers that tools and tests start on loopback. By default the system picks
# them (its ephemeral range). With SWARMLOC_PORT_RANGE=LO-HI they come from that range, tried
# from a random start: processes side by side (the test suite's workers) get disjoint ranges
# below the ephemeral one, so no other process takes a port between its pick and its bind.
PORT_RANGE_ENV = "SWARMLOC_PORT_RANGE"


def port_range() -> tuple[int, int] | None:
    """``SWARMLOC_PORT_RANGE`` as (lo, hi), hi exclusive; None when unset."""
    raw = os.environ.get(PORT_RANGE_ENV, "").strip()
    if not raw:
        return None
    lo_s, sep, hi_s = raw.partition("-")
    try:
        lo, hi = int(lo_s), int(hi_s)
    except ValueError:
        lo, hi = 0, 0
    if not sep or not 1024 <= lo < hi <= 65536:
        raise ValueError(f"{PORT_RANGE_ENV}={raw!r}: expected LO-HI with 1024 <= LO < HI <= "
                         "65536, e.g. 20000-26000")
    return lo, hi


def free_ports(n: int, host: str = "127.0.0.1") -> list[int]:
    """``n`` distinct ports that nothing listens on at the time of the call."""
    bounds = port_range()
    with contextlib.ExitStack() as stack:
        if bounds is None:
            socks = [stack.enter_context(socket.socket()) for _ in range(n)]
            for s in socks:
                s.bind((host, 0))
            return [int(s.getsockname()[1]) for s in socks]
        lo, hi = bounds
        start = random.SystemRandom().randrange(lo, hi)
        found: list[int] = []
        for k in range(hi - lo):
            port = lo + (start - lo + k) % (hi - lo)
            s = socket.socket()
            try:
                s.bind((host, port))
            except OSError:
                s.close()  # a taken port's socket is not held: a full range has many
                continue
            stack.enter_context(s)
            found.append(port)
            if len(found) == n:
                return found
        raise RuntimeError(f"{PORT_RANGE_ENV}: fewer than {n} free ports in {lo}-{hi}")


def free_port(host: str = "127.0.0.1") -> int:
    return free_ports(1, host)[0]


@contextlib.contextmanager
def running_server(service: LocalizationService, zenoh: bool = True,
                   timeout_s: float = 20.0) -> Iterator[str]:
    """uvicorn (and the Zenoh bridge) for ``service`` in a background thread; yields the base
    URL and stops the server on exit. Used by the latency benchmark and the tests."""
    s = service.settings
    hooks = [ZenohBridge(service)] if zenoh else []
    server = _Server(_uvicorn_config(create_app(service, lifespan_hooks=hooks), s, "warning"),
                     service)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + timeout_s
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            server.should_exit = True
            raise RuntimeError(f"the server did not start on {s.host}:{s.port}")
        time.sleep(0.05)
    try:
        yield f"http://{s.host}:{s.port}"
    finally:
        server.should_exit = True
        thread.join(timeout=timeout_s)
