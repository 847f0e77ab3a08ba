"""The estimate stream: newest wins, drops counted, particles only when asked, SSE over HTTP."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator

import httpx
import numpy as np
import pytest

from client.transports import HttpClient, ZenohClient
from service.api.models import Estimate, Hypothesis
from service.engine.events import EventHub, estimate_message
from service.engine.localization_service import LocalizationService
from service.engine.metrics import Metrics
from service.server import free_port, running_server
from service.settings import Settings

TOKEN = "events-test-token"


def _estimate(robot: str, seq: int, x: float = 1.0) -> Estimate:
    return Estimate(seq=seq, stamp=float(seq), frame_id="m", estimator="dpso", x=x, y=2.0,
                    heading=0.5, speed=0.6, status="tracking", lost=False, score=0.2,
                    comparisons=12, covariance=[[1.0, 0.0], [0.0, 1.0]],
                    pose_covariance=[0.0] * 36, accuracy_m=1.5, nearest_image=3,
                    nearest_image_name="3.png", spread_m=1.0, robot_id=robot)


def test_hypotheses_are_streamed_when_the_estimate_has_them() -> None:
    est = _estimate("a", 1).model_copy(update={"hypotheses": [
        Hypothesis(x=1.234, y=5.0, weight=0.7), Hypothesis(x=-3.0, y=2.0, weight=0.3)]})
    msg = json.loads(estimate_message(est, 1.0, None))
    assert msg["hypotheses"] == [[1.23, 5.0, 0.7], [-3.0, 2.0, 0.3]]
    assert "hypotheses" not in json.loads(estimate_message(_estimate("a", 1), 1.0, None))


class _Estimator:
    def __init__(self) -> None:
        self.reads = 0

    def particles(self) -> np.ndarray:
        self.reads += 1
        return np.array([[1.234, 2.0], [3.0, 4.0]])


class _Localizer:  # the one attribute the hub reads: estimator.particles()
    def __init__(self) -> None:
        self.estimator = _Estimator()


def test_slow_viewer_gets_the_newest_estimate_per_robot_and_drops_are_counted() -> None:
    async def scenario() -> list[dict]:
        metrics = Metrics()
        hub = EventHub(metrics)
        sub = hub.subscribe(asyncio.get_running_loop(), "m")
        other_map = hub.subscribe(asyncio.get_running_loop(), "elsewhere")
        for seq in range(1, 6):  # the viewer reads nothing meanwhile
            hub.publish(_estimate("a", seq, x=float(seq)), 0.02)
        hub.publish(_estimate("b", 1), 0.02)
        msgs = [json.loads(m) for m in await sub.take(1.0)]
        assert await other_map.take(0.05) == []
        assert metrics.events_dropped._value.get() == 4
        assert metrics.event_subscribers._value.get() == 2
        hub.unsubscribe(sub)
        hub.unsubscribe(other_map)
        assert metrics.event_subscribers._value.get() == 0
        return msgs

    msgs = asyncio.run(scenario())
    assert [(m["robot"], m["seq"], m["x"]) for m in msgs] == [("a", 5, 5.0), ("b", 1, 1.0)]
    a = msgs[0]
    assert a["status"] == "tracking" and a["accuracy_m"] == 1.5 and a["latency_ms"] == 20.0
    assert "covariance" not in a and len(json.dumps(a)) < 400


def test_particles_are_read_only_when_watched_and_at_most_once_per_interval() -> None:
    async def scenario() -> None:
        hub = EventHub(Metrics(), particle_interval_s=3600.0)
        loc = _Localizer()
        assert hub.particles_due("a", loc) is None  # nobody connected
        sub = hub.subscribe(asyncio.get_running_loop(), None)
        assert hub.particles_due("a", loc) is None  # connected, not watching particles
        assert loc.estimator.reads == 0
        hub.unsubscribe(sub)
        watcher = hub.subscribe(asyncio.get_running_loop(), None, ["a"])
        assert hub.particles_due("b", loc) is None and loc.estimator.reads == 0
        xy = hub.particles_due("a", loc)
        assert xy is not None and xy.shape == (2, 2) and loc.estimator.reads == 1
        assert hub.particles_due("a", loc) is None and loc.estimator.reads == 1  # rate limit
        hub.publish(_estimate("a", 1), None, xy)
        msgs = [json.loads(m) for m in await watcher.take(1.0)]
        assert [m["k"] for m in msgs] == ["e", "p"]
        assert msgs[1]["xy"] == [1.23, 2.0, 3.0, 4.0]

    asyncio.run(scenario())


@pytest.fixture(scope="module")
def guarded_server(tmp_path_factory: pytest.TempPathFactory, small_map) -> Iterator[dict]:
    from service.maps.route_map import save_map

    maps = tmp_path_factory.mktemp("events_maps")
    save_map(small_map, maps / "small")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = Settings(maps_dir=maps, host="127.0.0.1", port=free_port(), auth_token=TOKEN,
                        zenoh_listen=[endpoint], zenoh_multicast_scouting=False, workers=2,
                        zenoh_unauthenticated=True)  # loopback only, accepted here
    service = LocalizationService(settings)
    with running_server(service) as url:
        yield {"url": url, "zenoh": endpoint, "service": service}


def _batches(lines: Iterator[str]) -> Iterator[dict]:
    for line in lines:
        if line.startswith("data:"):
            yield json.loads(line[5:])


def test_sse_stream_over_http_carries_both_transports(guarded_server, sunny2) -> None:
    url = guarded_server["url"]
    with httpx.Client(base_url=url, timeout=30) as http:
        r = http.get("/events")
        assert r.status_code == 401 and "?token=" in r.json()["error"]
        r = http.get("/events", params={"map": "nope", "token": TOKEN})
        assert r.status_code == 404 and "small" in r.json()["error"]

    api = HttpClient(url, token=TOKEN)
    z = ZenohClient([guarded_server["zenoh"]], mode="peer")
    frame = sunny2.image_path(10).read_bytes()
    try:
        api.create_session("ev-http", "small", "dpso", seed=1)
        api.localize("ev-http", frame, t=0.0)  # before the viewer: comes in the first batch
        n_particles = z.create_session("ev-zenoh", "small", "pf-l", seed=2).params["n_particles"]
        headers = {"Authorization": f"Bearer {TOKEN}"}
        params = {"map": "small", "particles": "ev-zenoh"}
        with httpx.stream("GET", f"{url}/events", params=params, headers=headers,
                          timeout=30) as resp:
            assert resp.status_code == 200
            assert resp.headers["content-type"].startswith("text/event-stream")
            batches = _batches(resp.iter_lines())
            first = next(batches)
            assert [(m["k"], m["robot"]) for m in first["m"]] == [("e", "ev-http")]
            z.localize("ev-zenoh", frame, t=0.0)
            seen: list[dict] = []
            while not {"e", "p"} <= {m["k"] for m in seen if m["robot"] == "ev-zenoh"}:
                seen += next(batches)["m"]
            est = next(m for m in seen if m["k"] == "e")
            assert est["seq"] == 1 and est["map"] == "small" and est["latency_ms"] > 0
            part = next(m for m in seen if m["k"] == "p")
            assert len(part["xy"]) == 2 * n_particles  # x and y of every particle
            api.delete_session("ev-http")
            seen = []
            while not any(m["k"] == "x" for m in seen):
                seen += next(batches)["m"]
            assert {"k": "x", "robot": "ev-http"} in seen
        metrics = httpx.get(f"{url}/metrics", headers=headers).text
        assert "swarmloc_events_published_total" in metrics
        assert "swarmloc_events_dropped_total" in metrics
    finally:
        api.close()
        z.close()


def test_shutdown_ends_open_streams_cleanly(tmp_path, small_map) -> None:
    """Open streams end with a complete response when the server stops (not cut off)."""
    import threading

    from service.maps.route_map import save_map

    save_map(small_map, tmp_path / "small")
    settings = Settings(maps_dir=tmp_path, host="127.0.0.1", port=free_port(),
                        zenoh_enabled=False)
    service = LocalizationService(settings)
    outcome: dict = {}

    def read(url: str) -> None:
        try:
            with httpx.stream("GET", f"{url}/events", timeout=30) as resp:
                outcome["lines"] = list(resp.iter_lines())
        except Exception as exc:  # a cut-off stream raises RemoteProtocolError here
            outcome["error"] = exc

    with running_server(service, zenoh=False) as url:
        reader = threading.Thread(target=read, args=(url,))
        reader.start()
        deadline = 200
        while service.events.subscribers == 0 and deadline:
            threading.Event().wait(0.05)
            deadline -= 1
        assert service.events.subscribers == 1
    reader.join(30)
    assert not reader.is_alive()
    assert "error" not in outcome, outcome.get("error")
    assert outcome["lines"][0] == "retry: 2000"
    assert service.events.subscribers == 0
