"""Several real ``swarmloc serve`` replicas sharing a real ``redis-server``.

Replica A also routes Zenoh (mode router, like zenohd in deploy/compose.yaml); replica B (a
Zenoh peer) and the robot (a client) connect to it. Every estimate is checked against one
in-process service that sees the same frames: bit for bit, whichever replica made it.
"""

from __future__ import annotations

import dataclasses
import json
import signal
import threading
import time
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import zenoh

from client.lab.processes import RedisServer, ServiceProcess
from service.api.models import Estimate, SessionConfig
from service.engine.localization_service import LocalizationService
from service.engine.localizer import Localizer
from service.engine.store import RedisOptions, RedisStore, Session
from service.maps.route_map import RouteMap, save_map
from service.server import free_ports
from service.settings import Settings
from tests.replicas import upload_served_by_the_other

SEED = 7
LEARN_FRAMES = 16  # cloudy frames each learning robot sends


@pytest.fixture(scope="module")
def maps_dir(tmp_path_factory: pytest.TempPathFactory, small_map: RouteMap) -> Path:
    d = tmp_path_factory.mktemp("replica_maps")
    save_map(small_map, d / "small")
    save_map(dataclasses.replace(small_map, name="learn"), d / "learn")  # the robots teach it
    return d


@pytest.fixture(scope="module")
def replicas(tmp_path_factory: pytest.TempPathFactory, redis_srv: RedisServer,
             maps_dir: Path) -> Iterator[dict[str, Any]]:
    logs = tmp_path_factory.mktemp("replica_logs")
    # three distinct ports: two free_port() calls in a row once gave both replicas one port
    zenoh_port, port_a, port_b = free_ports(3)
    zenoh_ep = f"tcp/127.0.0.1:{zenoh_port}"
    common = {"SWARMLOC_MAPS_DIR": str(maps_dir), "SWARMLOC_SESSION_STORE": redis_srv.url,
              "SWARMLOC_ZENOH_MULTICAST_SCOUTING": "false", "SWARMLOC_WORKERS": "2",
              "SWARMLOC_SESSION_LOCK_WAIT_S": "30", "SWARMLOC_DEFAULT_MAP": "small",
              # learning: a batch every few taught frames, a gate 1 the short stretch passes
              "SWARMLOC_LEARN_COMMIT_IMAGES": "3", "SWARMLOC_LEARN_ACCURACY_M": "2.0"}
    a = ServiceProcess("replica-a", {**common, "SWARMLOC_ZENOH_MODE": "router",
                                     "SWARMLOC_ZENOH_LISTEN": json.dumps([zenoh_ep])}, logs,
                       port=port_a)
    b = ServiceProcess("replica-b", {**common, "SWARMLOC_ZENOH_MODE": "peer",
                                     "SWARMLOC_ZENOH_LISTEN": "[]",
                                     "SWARMLOC_ZENOH_CONNECT": json.dumps([zenoh_ep])}, logs,
                       port=port_b)
    a.start()
    b.start()
    try:
        a.wait_ready()
        b.wait_ready()
        yield {"a": a, "b": b, "zenoh": zenoh_ep}
    finally:
        a.stop()
        b.stop()


@pytest.fixture(scope="module")
def frames(sunny2) -> list[bytes]:
    return [sunny2.image_path(i).read_bytes() for i in range(10, 22)]


class Reference:
    """One in-process service: what a single process answers to the same frames."""

    def __init__(self, small_map: RouteMap, robot: str, estimator: str = "dpso") -> None:
        self.svc = LocalizationService(Settings(zenoh_enabled=False),
                                       maps={small_map.name: small_map})
        self.robot = robot
        self.svc.put_session(robot, SessionConfig(map="small", estimator=estimator, seed=SEED))

    def frame(self, data: bytes, k: int) -> dict[str, Any]:
        est = self.svc.process_frame(self.robot, data, content_type="image/png",
            t=float(k), input_seq=k)
        return est.model_dump()


def _create(url: str, robot: str, estimator: str = "dpso") -> None:
    r = httpx.put(f"{url}/sessions/{robot}", timeout=30,
                  json={"map": "small", "estimator": estimator, "seed": SEED})
    assert r.status_code in (200, 201), r.text


def _post(url: str, robot: str, data: bytes, k: int) -> httpx.Response:
    return httpx.post(f"{url}/sessions/{robot}/frames", params={"t": float(k), "seq": k},
                      content=data, headers={"Content-Type": "image/png"}, timeout=60)


def _est(r: httpx.Response) -> dict[str, Any]:
    assert r.status_code == 200, r.text
    return Estimate.model_validate(r.json()).model_dump()


def _frames_of(url: str, robot: str) -> int:
    r = httpx.get(f"{url}/sessions/{robot}", timeout=30)
    assert r.status_code == 200, r.text
    return int(r.json()["frames"])


def test_frames_alternating_between_replicas_equal_one_process(
        replicas, rdb, frames, small_map) -> None:
    a, b = replicas["a"].url, replicas["b"].url
    for estimator in ("dpso", "pf-l"):
        robot = f"alt-{estimator}"
        ref = Reference(small_map, robot, estimator)
        _create(a, robot, estimator)
        for k, data in enumerate(frames[:8]):
            got = _est(_post(a if k % 2 == 0 else b, robot, data, k))
            assert got == ref.frame(data, k), f"{estimator} frame {k}"
        assert _frames_of(a, robot) == _frames_of(b, robot) == 8


def test_a_repeated_frame_is_answered_not_applied(replicas, rdb, frames) -> None:
    a, b = replicas["a"].url, replicas["b"].url
    _create(a, "dup")
    first = _est(_post(a, "dup", frames[0], 0))
    second = _est(_post(a, "dup", frames[1], 1))
    again = _est(_post(b, "dup", frames[1], 1))  # a retry that reached the other replica
    assert again == second and again != first
    assert _frames_of(b, "dup") == 2
    old = _post(b, "dup", frames[0], 0)
    assert old.status_code == 409 and "older than the last" in old.json()["error"]
    # the same seq with another timestamp is a new frame (e.g. a robot that restarted)
    r = httpx.post(f"{a}/sessions/dup/frames", params={"t": 2.0, "seq": 1},
                   content=frames[2], headers={"Content-Type": "image/png"}, timeout=60)
    assert _est(r)["seq"] == 3
    assert _frames_of(a, "dup") == 3


def test_concurrent_frames_for_one_robot_on_two_replicas(replicas, rdb, frames,
                                                          small_map) -> None:
    """Both replicas get the same frame at once: it is applied once and both answer it."""
    a, b = replicas["a"].url, replicas["b"].url
    ref = Reference(small_map, "both")
    _create(b, "both")

    def send(go: threading.Barrier, answers: dict[str, httpx.Response], name: str, url: str,
             data: bytes, k: int) -> None:
        go.wait()
        answers[name] = _post(url, "both", data, k)

    for k, data in enumerate(frames[:4]):
        answers: dict[str, httpx.Response] = {}
        go = threading.Barrier(2)
        threads = [threading.Thread(target=send, args=(go, answers, n, u, data, k))
                   for n, u in (("a", a), ("b", b))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        expected = ref.frame(data, k)
        assert _est(answers["a"]) == _est(answers["b"]) == expected
    assert _frames_of(a, "both") == 4


def test_a_crashed_holders_lock_expires(replicas, rdb, frames) -> None:
    a = replicas["a"].url
    _create(a, "held")
    # a replica that took the robot's lock and died: nobody releases it, its lease runs out
    rdb.set("swarmloc:lock:held", "dead-replica", px=1500)
    r = _post(a, "held", frames[0], 0)  # waits (up to 30 s here) and then goes ahead
    assert r.status_code == 200, r.text
    assert rdb.get("swarmloc:lock:held") is None
    assert _frames_of(a, "held") == 1


def _zenoh_client(endpoint: str) -> zenoh.Session:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(cfg)


def test_zenoh_exactly_one_replica_serves_each_robot(replicas, rdb, frames) -> None:
    robots = ["z1", "z2", "z3"]
    published: dict[str, list[dict[str, Any]]] = defaultdict(list)
    z = _zenoh_client(replicas["zenoh"])
    try:
        sub = z.declare_subscriber(
            "swarmloc/*/estimate",
            lambda s: published[str(s.key_expr).split("/")[1]].append(
                json.loads(s.payload.to_bytes())))
        time.sleep(0.5)  # both replicas' declarations reach the client through the router
        for robot in robots:  # queries: every queryable is asked, one replica answers
            for k in range(2):
                replies = list(z.get(
                    f"swarmloc/{robot}/localize", payload=frames[k],
                    attachment=json.dumps({"t": float(k), "seq": k}).encode(),
                    target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
                    timeout=60.0))
                assert len(replies) == 1, f"{robot}: {len(replies)} replies"
                assert replies[0].ok is not None, str(replies[0].err)
                assert json.loads(replies[0].ok.payload.to_bytes())["seq"] == k + 1
        for robot in robots:  # published frames: one estimate each, from one replica
            for k in range(2, 4):
                n = len(published[robot])
                z.put(f"swarmloc/{robot}/frame", frames[k],
                      attachment=json.dumps({"t": float(k), "seq": k}).encode())
                deadline = time.monotonic() + 60
                while len(published[robot]) == n and time.monotonic() < deadline:
                    time.sleep(0.02)
        time.sleep(1.0)  # a second replica's answer would arrive by now
        sub.undeclare()
    finally:
        z.close()
    for robot in robots:
        seqs = [e.get("input_seq") for e in published[robot]]
        assert seqs == [2, 3], f"{robot}: {published[robot]}"
        assert [e["seq"] for e in published[robot]] == [3, 4]
        assert _frames_of(replicas["b"].url, robot) == 4  # not 8: no frame went twice
    owners = {rdb.get(f"swarmloc:claim:{r}") for r in robots}
    assert owners <= {b"replica-a", b"replica-b"} and None not in owners


def test_redis_restart_mid_stream(replicas, rdb, redis_srv, frames, small_map) -> None:
    """Redis down: clear 503s, nothing applied; Redis back (append-only file): the stream
    continues where it was, bit for bit."""
    a, b = replicas["a"].url, replicas["b"].url
    ref = Reference(small_map, "rr")
    _create(a, "rr")
    for k in range(3):
        assert _est(_post(a if k % 2 else b, "rr", frames[k], k)) == ref.frame(frames[k], k)
    redis_srv.stop()
    try:
        for url in (a, b):
            r = _post(url, "rr", frames[3], 3)
            assert r.status_code == 503, r.text
            assert "session store unavailable" in r.json()["error"]
        assert httpx.get(f"{a}/sessions/rr", timeout=30).status_code == 503
    finally:
        redis_srv.start()
    for k in range(3, 6):
        assert _est(_post(b if k % 2 else a, "rr", frames[k], k)) == ref.frame(frames[k], k)
    assert _frames_of(a, "rr") == 6


def test_kill_9_of_a_replica_mid_stream(replicas, rdb, frames, small_map) -> None:
    """A replica dies (SIGKILL) mid-stream: the robot goes on on the other one, and on the
    restarted replica: no session lost, no frame repeated, no re-initialisation."""
    a, b = replicas["a"], replicas["b"]
    ref = Reference(small_map, "k9")
    _create(a.url, "k9")
    expected = [ref.frame(data, k) for k, data in enumerate(frames[:9])]
    for k in range(3):
        assert _est(_post(a.url, "k9", frames[k], k)) == expected[k]
    assert a.stop(signal.SIGKILL) == -signal.SIGKILL
    # the robot's answer to frame 2 may have been lost: it sends it again to the other one
    assert _est(_post(b.url, "k9", frames[2], 2)) == expected[2]
    for k in range(3, 6):
        assert _est(_post(b.url, "k9", frames[k], k)) == expected[k]
    a.start().wait_ready()
    for k in range(6, 9):
        assert _est(_post(a.url, "k9", frames[k], k)) == expected[k]
    assert _frames_of(a.url, "k9") == 9


def test_a_state_from_another_version_is_refused_with_a_way_out(
        replicas, rdb, redis_srv, frames, small_map) -> None:
    """A state written by a swarmloc whose estimator had other attributes (a replica of the
    previous release, mid-upgrade) is never half-read: its robot gets a 409 that says how
    to start over, every other robot is served, and the listing leaves it out."""
    a, b = replicas["a"].url, replicas["b"].url
    _create(a, "current")
    _est(_post(a, "current", frames[0], 0))
    older = Localizer(small_map, "dpso", None, SEED)
    del older.estimator.smoother  # type: ignore[attr-defined]  # before along-track smoothing
    store = RedisStore(redis_srv.url, lambda *_: small_map, RedisOptions())
    store.create(Session("older", older, time.time(), time.time()), True, 100)
    for url in (a, b):
        r = _post(url, "older", frames[0], 0)
        assert r.status_code == 409, r.text
        err = r.json()["error"]
        assert "missing ['smoother']" in err and "PUT /sessions/older" in err
    assert _est(_post(b, "current", frames[1], 1))["status"]  # everyone else is served
    listed = httpx.get(f"{a}/sessions", timeout=30)
    assert listed.status_code == 200, listed.text
    assert [s["robot_id"] for s in listed.json()] == ["current"]
    _create(a, "older")  # the way out: start it over
    _est(_post(b, "older", frames[0], 0))
    assert _frames_of(a, "older") == 1


def test_two_robots_learn_on_two_replicas_one_writer_both_serve_it(
        replicas, rdb, cloudy1) -> None:
    """Two learning robots, one on each replica, at once: the batches of both go through the
    map's list in Redis to the one replica that holds the writer lease; no update is lost,
    and both replicas serve the new version (the same ETag) without a restart."""
    a, b = replicas["a"].url, replicas["b"].url
    before = httpx.get(f"{a}/maps/learn", timeout=30).headers["ETag"]
    robots = {"learner-a": a, "learner-b": b}
    for robot, url in robots.items():
        r = httpx.put(f"{url}/sessions/{robot}", timeout=30, json={
            "map": "learn", "learn": True, "condition": "cloudy", "seed": SEED})
        assert r.status_code == 201, r.text
    frames = [cloudy1.image_path(i).read_bytes() for i in range(LEARN_FRAMES)]
    answers: dict[str, list[int]] = defaultdict(list)

    def drive(robot: str, url: str) -> None:
        for k, data in enumerate(frames):
            answers[robot].append(_post(url, robot, data, k).status_code)

    threads = [threading.Thread(target=drive, args=item) for item in robots.items()]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(answers[r] == [200] * LEARN_FRAMES for r in robots), answers
    for robot, url in robots.items():  # the end of a session hands its last images over
        assert httpx.delete(f"{url}/sessions/{robot}", timeout=30).status_code == 204
    deadline = time.monotonic() + 60
    while not _all_written(rdb, (a, b)) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert _all_written(rdb, (a, b))
    got = {n: httpx.get(f"{url}/maps/learn", timeout=30) for n, url in (("a", a), ("b", b))}
    learned = {n: sorted(str(e["robot"]) for e in r.json()["experiences"])
               for n, r in got.items()}
    assert learned["a"] == learned["b"] == sorted(robots), learned  # no lost update
    etag = got["a"].headers["ETag"]
    assert got["b"].headers["ETag"] == etag != before  # both serve the new version


def test_a_map_uploaded_or_deleted_through_one_replica_on_the_other(
        replicas, frames, small_map, tmp_path: Path) -> None:
    """Replicas on one maps directory: a map uploaded through A is served by B (the same
    ETag, listed, a robot localizes on it through B) without a restart; deleted through A,
    it ends the robot's session and B no longer serves it."""
    a, b = replicas["a"].url, replicas["b"].url
    data = save_map(dataclasses.replace(small_map, name="shared"), tmp_path / "shared"
                    ).read_bytes()
    upload_served_by_the_other(a, b, "shared", data, "sharer", frames[0], SEED)
    r = httpx.delete(f"{a}/maps/shared", params={"force": "true"}, timeout=30)
    assert r.status_code == 200 and r.json()["ended_sessions"] == ["sharer"], r.text
    assert httpx.get(f"{b}/maps/shared", timeout=30).status_code == 404
    assert "shared" not in [m["name"] for m in httpx.get(f"{b}/maps", timeout=30).json()]
    assert httpx.get(f"{b}/sessions/sharer", timeout=30).status_code == 404


def _all_written(rdb, urls: tuple[str, ...]) -> bool:
    """No learned batch waits in a replica, in the map's list or in a write (the lease)."""
    for url in urls:
        text = httpx.get(f"{url}/metrics", timeout=30).text
        if "swarmloc_learned_batches_waiting 0.0" not in text:
            return False
    return rdb.llen("swarmloc:learn:learn") == 0 and rdb.get("swarmloc:writer:learn") is None
