"""Shared fixtures: a small rendered world, its rounds and a map built from one of them.

Everything is rendered here, into pytest's temporary directories; nothing from ../shared.
"""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import pytest
import uvicorn

from client.dataset import Round, read_round
from client.world import World
from service.http_api import create_app
from service.route_map import RouteMap, build_map, load_map, save_map
from service.sessions import LocalizationService
from service.settings import Settings
from service.zenoh_bridge import ZenohBridge

SMALL_LENGTH_M = 90.0


@pytest.fixture(scope="session")
def small_world() -> World:
    return World(seed=3, length_m=SMALL_LENGTH_M)


@pytest.fixture(scope="session")
def rounds_dir(tmp_path_factory: pytest.TempPathFactory, small_world: World) -> Path:
    root = tmp_path_factory.mktemp("world")
    small_world.render_round(root / "sunny1", 0, "sunny")
    small_world.render_round(root / "sunny2", 1, "sunny")
    small_world.render_round(root / "cloudy1", 3, "cloudy")
    return root


@pytest.fixture(scope="session")
def sunny1(rounds_dir: Path) -> Round:
    return read_round(rounds_dir / "sunny1")


@pytest.fixture(scope="session")
def sunny2(rounds_dir: Path) -> Round:
    return read_round(rounds_dir / "sunny2")


@pytest.fixture(scope="session")
def cloudy1(rounds_dir: Path) -> Round:
    return read_round(rounds_dir / "cloudy1")


@pytest.fixture(scope="session")
def small_map(tmp_path_factory: pytest.TempPathFactory, sunny1: Round) -> RouteMap:
    m = build_map("small", [sunny1.load_image(i) for i in range(len(sunny1))], sunny1.xy,
                  list(sunny1.images))
    path = save_map(m, tmp_path_factory.mktemp("maps") / "small")
    return load_map(path)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory, small_map):
    maps = tmp_path_factory.mktemp("srv_maps")
    save_map(small_map, maps / "small")
    port, zport = free_port(), free_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    settings = Settings(maps_dir=maps, host="127.0.0.1", port=port, zenoh_listen=[endpoint],
                        zenoh_multicast_scouting=False, workers=4)
    service = LocalizationService(settings)
    app = create_app(service, lifespan_hooks=[ZenohBridge(service)])
    srv = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    th = threading.Thread(target=srv.run, daemon=True)
    th.start()
    deadline = time.time() + 20
    while not srv.started and time.time() < deadline:
        time.sleep(0.05)
    assert srv.started
    yield {"url": f"http://127.0.0.1:{port}", "zenoh": endpoint, "maps": maps,
           "service": service}
    srv.should_exit = True
    th.join(timeout=20)
