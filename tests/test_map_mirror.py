"""Replicas with a maps directory each (``SWARMLOC_MAPS_SYNC=redis``): map files travel
through a real ``redis-server`` between real ``swarmloc serve`` processes.

The replicas use their own Redis database (1; 2 for the in-process pair of the race test),
so the other modules' emptied database 0 never takes their maps away.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from client.lab.processes import RedisServer, ServiceProcess
from service.api.errors import PreconditionFailed
from service.engine.localization_service import LocalizationService
from service.maps.route_map import RouteMap, file_version, save_map
from service.settings import Settings
from tests.replicas import upload_served_by_the_other

SEED = 7


def _db(redis_srv: RedisServer, n: int) -> str:
    return redis_srv.url.rsplit("/", 1)[0] + f"/{n}"


@pytest.fixture(scope="module")
def mirrored(tmp_path_factory: pytest.TempPathFactory, redis_srv: RedisServer,
             small_map: RouteMap) -> Iterator[dict[str, Any]]:
    import redis

    r = redis.Redis.from_url(_db(redis_srv, 1))
    r.flushdb()
    dir_a, dir_b = tmp_path_factory.mktemp("maps_a"), tmp_path_factory.mktemp("maps_b")
    save_map(small_map, dir_a / "small")  # only A has it on disk
    logs = tmp_path_factory.mktemp("mirror_logs")
    common = {"SWARMLOC_SESSION_STORE": _db(redis_srv, 1), "SWARMLOC_MAPS_SYNC": "redis",
              "SWARMLOC_ZENOH_ENABLED": "false", "SWARMLOC_WORKERS": "2",
              "SWARMLOC_DEFAULT_MAP": "small",
              "SWARMLOC_LEARN_COMMIT_IMAGES": "3", "SWARMLOC_LEARN_ACCURACY_M": "2.0"}
    a = ServiceProcess("mirror-a", {**common, "SWARMLOC_MAPS_DIR": str(dir_a)}, logs)
    b = ServiceProcess("mirror-b", {**common, "SWARMLOC_MAPS_DIR": str(dir_b)}, logs)
    a.start().wait_ready()  # A publishes its map first
    b.start().wait_ready()
    try:
        yield {"a": a, "b": b, "dir_a": dir_a, "dir_b": dir_b, "redis": r}
    finally:
        a.stop()
        b.stop()
        r.close()


def _upload(url: str, name: str, data: bytes, **headers: str) -> httpx.Response:
    return httpx.put(f"{url}/maps/{name}", content=data, timeout=60,
                     headers={"content-type": "application/octet-stream", **headers})


def _version(small_map: RouteMap, name: str, tag: str, tmp: Path) -> bytes:
    """A file of map ``name``: the small map with its own version (``tag`` in its
    metadata)."""
    m = dataclasses.replace(small_map, name=name, meta={**small_map.meta, "note": tag})
    return save_map(m, tmp / f"{name}-{tag}").read_bytes()


def test_a_map_on_one_replicas_disk_is_served_by_the_other(mirrored) -> None:
    a, b = mirrored["a"].url, mirrored["b"].url
    got_a = httpx.get(f"{a}/maps/small", timeout=30)
    got_b = httpx.get(f"{b}/maps/small", timeout=30)
    assert got_b.status_code == 200 and got_b.headers["ETag"] == got_a.headers["ETag"]
    assert file_version(mirrored["dir_b"] / "small.swmap") == got_a.headers["ETag"].strip('"')


def test_upload_replace_and_delete_reach_the_other_replica(
        mirrored, small_map, sunny2, tmp_path: Path) -> None:
    """Uploaded through A, served by B (a robot localizes there); replaced through B with
    If-Match, then an upload through A against the old version is refused (412); deleted
    through A, B no longer serves it and its file is gone."""
    a, b = mirrored["a"].url, mirrored["b"].url
    first = upload_served_by_the_other(a, b, "street",
                                       _version(small_map, "street", "v1", tmp_path),
                                       "walker", sunny2.image_path(10).read_bytes(), SEED)
    second = _upload(b, "street", _version(small_map, "street", "v2", tmp_path),
                     **{"if-match": first})
    assert second.status_code == 200, second.text
    assert httpx.get(f"{a}/maps/street", timeout=30).headers["ETag"] == second.headers["ETag"]
    stale = _upload(a, "street", _version(small_map, "street", "v3", tmp_path),
                    **{"if-match": first})
    assert stale.status_code == 412, stale.text
    gone = httpx.delete(f"{a}/maps/street", params={"force": "true"}, timeout=30)
    assert gone.status_code == 200 and gone.json()["ended_sessions"] == ["walker"], gone.text
    assert httpx.get(f"{b}/maps/street", timeout=30).status_code == 404
    assert "street" not in [m["name"] for m in httpx.get(f"{b}/maps", timeout=30).json()]
    assert not (mirrored["dir_b"] / "street.swmap").exists()


def test_a_replica_down_during_a_delete_drops_its_copy_when_back(
        mirrored, small_map, tmp_path: Path) -> None:
    a, b = mirrored["a"], mirrored["b"]
    r = _upload(a.url, "brief", _version(small_map, "brief", "v1", tmp_path))
    assert r.status_code == 201, r.text
    assert httpx.get(f"{b.url}/maps/brief", timeout=30).status_code == 200
    assert (mirrored["dir_b"] / "brief.swmap").exists()
    b.stop()
    try:
        assert httpx.delete(f"{a.url}/maps/brief", timeout=30).status_code == 200
    finally:
        b.start().wait_ready()
    assert httpx.get(f"{b.url}/maps/brief", timeout=30).status_code == 404
    assert not (mirrored["dir_b"] / "brief.swmap").exists()  # not published again


def test_a_learning_robot_on_one_replica_teaches_the_others_map(mirrored, cloudy1) -> None:
    a, b = mirrored["a"].url, mirrored["b"].url
    before = httpx.get(f"{a}/maps/small", timeout=30).headers["ETag"]
    r = httpx.put(f"{b}/sessions/teacher", timeout=30, json={
        "map": "small", "learn": True, "condition": "cloudy", "seed": SEED})
    assert r.status_code == 201, r.text
    for k in range(16):
        got = httpx.post(f"{b}/sessions/teacher/frames", params={"t": float(k), "seq": k},
                         content=cloudy1.image_path(k).read_bytes(),
                         headers={"Content-Type": "image/png"}, timeout=60)
        assert got.status_code == 200, got.text
    assert httpx.delete(f"{b}/sessions/teacher", timeout=30).status_code == 204
    deadline = time.monotonic() + 60
    while not _all_written(mirrored["redis"], b) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert _all_written(mirrored["redis"], b)
    got = {n: httpx.get(f"{url}/maps/small", timeout=30) for n, url in (("a", a), ("b", b))}
    assert got["a"].headers["ETag"] == got["b"].headers["ETag"] != before
    assert {e["robot"] for e in got["a"].json()["experiences"]} == {"teacher"}


def _all_written(r: Any, url: str) -> bool:
    """No learned batch waits in the replica, in the map's list or in a write (the lease)."""
    text = httpx.get(f"{url}/metrics", timeout=30).text
    return "swarmloc_learned_batches_waiting 0.0" in text and \
        r.llen("swarmloc:learn:small") == 0 and r.get("swarmloc:writer:small") is None


def test_a_publish_from_a_stale_version_is_refused(redis_srv, small_map, tmp_path: Path
                                                   ) -> None:
    """Two replicas that replace one map at once from the same version: the second one's
    publish is refused (412), not written over the first."""
    url = _db(redis_srv, 2)
    import redis

    redis.Redis.from_url(url).flushdb()
    services = []
    for side in ("a", "b"):
        d = tmp_path / side
        d.mkdir()
        services.append(LocalizationService(Settings(
            maps_dir=d, session_store=url, maps_sync="redis", zenoh_enabled=False)))
    one, two = services
    try:
        v1 = _version(small_map, "race", "v1", tmp_path)
        v2 = _version(small_map, "race", "v2", tmp_path)
        staged = [one.admin.staging_file("upload"), two.admin.staging_file("upload")]
        for path, data in zip(staged, (v1, v2), strict=True):
            path.write_bytes(data)
        # both started from "no such map": the first publish wins, the second is refused
        one.admin._publish("race", staged[0], file_version(staged[0]), None)
        with pytest.raises(PreconditionFailed, match="another replica"):
            two.admin._publish("race", staged[1], file_version(staged[1]), None)
        assert one.admin.mirror is not None
        head = one.admin.mirror.head("race")
        assert head is not None and not head.deleted
        assert head.version == file_version(staged[0]) != file_version(staged[1])
    finally:
        for svc in services:
            svc.close()


def test_maps_through_redis_need_the_redis_store(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="needs the Redis session store"):
        Settings(maps_dir=tmp_path, maps_sync="redis")


def test_a_damaged_file_in_redis_is_not_taken(mirrored, small_map, tmp_path: Path) -> None:
    """A published file whose bytes no longer match its checksum (its header intact) never
    replaces a replica's copy: the replica that lacks it does not serve it."""
    a, b = mirrored["a"].url, mirrored["b"].url
    r = _upload(a, "dented", _version(small_map, "dented", "v1", tmp_path))
    assert r.status_code == 201, r.text
    key = "swarmloc:mapfile:dented"
    data = bytearray(mirrored["redis"].hget(key, "data"))
    data[-100] ^= 0xFF  # in the arrays, after the header
    mirrored["redis"].hset(key, "data", bytes(data))
    assert httpx.get(f"{b}/maps/dented", timeout=30).status_code == 404
    assert not (mirrored["dir_b"] / "dented.swmap").exists()
    assert "damaged, not taken" in mirrored["b"].log_tail(20000)
