"""Session stores: fleet-wide limits and expiry, locks, compare-and-set, snapshots.

Two ``LocalizationService`` objects on one real redis-server act as two replicas here (cheap);
tests/test_scale_out.py runs real replica processes.
"""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path
from typing import Any

import httpx
import pytest

from client.lab.processes import RedisServer, ServiceProcess
from service.api.errors import Conflict, NotFound, Unavailable
from service.api.models import SessionConfig
from service.engine.localization_service import LocalizationService
from service.maps.route_map import RouteMap, load_map, save_map
from service.settings import Settings

SEED = 3


@pytest.fixture(scope="module")
def frames(sunny2) -> list[bytes]:
    return [sunny2.image_path(i).read_bytes() for i in range(4, 12)]


def _replica(small_map: RouteMap, **settings: Any) -> LocalizationService:
    return LocalizationService(Settings(zenoh_enabled=False, **settings),
                               maps={small_map.name: small_map})


def _config() -> SessionConfig:
    return SessionConfig(map="small", seed=SEED)


def _frame(svc: LocalizationService, robot: str, data: bytes, k: int) -> dict[str, Any]:
    return svc.process_frame(robot, data, content_type="image/png",
                             t=float(k), input_seq=k).model_dump()


def test_session_limit_is_fleet_wide(redis_srv: RedisServer, rdb, small_map) -> None:
    a = _replica(small_map, session_store=redis_srv.url, max_sessions=2)
    b = _replica(small_map, session_store=redis_srv.url, max_sessions=2)
    a.put_session("r1", _config())
    b.put_session("r2", _config())
    with pytest.raises(Unavailable, match="session limit of 2"):
        a.put_session("r3", _config())
    assert b.put_session("r1", _config())[1] is False  # replacing one is not a new one
    a.delete_session("r2")
    assert b.put_session("r3", _config())[1] is True
    assert sorted(s.robot_id for s in a.sessions()) == ["r1", "r3"]


def test_idle_sessions_expire_with_redis_ttls(redis_srv: RedisServer, rdb, small_map) -> None:
    a = _replica(small_map, session_store=redis_srv.url, max_sessions=1, session_idle_s=1.0)
    b = _replica(small_map, session_store=redis_srv.url, max_sessions=1, session_idle_s=1.0)
    a.put_session("idle", _config())
    assert 0 < rdb.pttl("swarmloc:s:idle") <= 1000
    with pytest.raises(Unavailable):
        b.put_session("other", _config())  # the limit of 1 holds across replicas
    time.sleep(1.3)
    assert rdb.exists("swarmloc:s:idle") == 0  # Redis ended it
    with pytest.raises(NotFound):
        b.session("idle")
    assert a.expire_idle() == ["idle"]  # viewers are told; the index forgets it
    b.put_session("other", _config())  # the slot is free again


def test_a_busy_robot_gives_409_and_nothing_changes(redis_srv: RedisServer, rdb, small_map,
                                                    frames) -> None:
    a = _replica(small_map, session_store=redis_srv.url, session_lock_wait_s=0.2)
    a.put_session("busy", _config())
    rdb.set("swarmloc:lock:busy", "another-replica", px=30_000)
    before = rdb.hget("swarmloc:s:busy", "st")
    with pytest.raises(Conflict, match="busy with another frame"):
        _frame(a, "busy", frames[0], 0)
    assert rdb.hget("swarmloc:s:busy", "st") == before
    assert rdb.get("swarmloc:lock:busy") == b"another-replica"  # not ours to release


def test_a_frame_whose_lease_ran_out_is_not_applied(redis_srv: RedisServer, rdb, small_map,
                                                    frames) -> None:
    """Replica A holds the lock past its lease; B goes ahead; A's late write is refused."""
    a = _replica(small_map, session_store=redis_srv.url)
    b = _replica(small_map, session_store=redis_srv.url)
    ref = _replica(small_map)
    for svc in (a, ref):
        svc.put_session("slow", _config())
    with pytest.raises(Conflict, match="changed meanwhile"):
        with a.store.locked("slow") as s:
            s.localizer.seq += 100  # A's change, never to be seen
            rdb.delete("swarmloc:lock:slow")  # the lease ran out
            _frame(b, "slow", frames[0], 0)
    assert b.session("slow").localizer.seq == 1
    _frame(ref, "slow", frames[0], 0)
    assert _frame(a, "slow", frames[1], 1) == _frame(ref, "slow", frames[1], 1)
    assert a.session("slow").localizer.seq == 2


def test_a_replaced_map_version_asks_for_a_reset(redis_srv: RedisServer, rdb, small_map,
                                                 frames, tmp_path: Path) -> None:
    a = _replica(small_map, session_store=redis_srv.url)
    a.put_session("mv", _config())
    other = load_map(save_map(small_map, tmp_path / "small"))
    other.meta["checksum"] = "f" * 64  # as if the map had been rebuilt and replaced
    b = LocalizationService(Settings(zenoh_enabled=False, session_store=redis_srv.url),
                            maps={"small": other})
    with pytest.raises(Conflict, match="reset the session"):
        _frame(b, "mv", frames[0], 0)
    info = b.reset_session("mv", None)
    assert info.map_checksum == "f" * 64
    assert _frame(b, "mv", frames[0], 0)["seq"] == 1


def test_in_process_snapshot_round_trip(small_map, frames, tmp_path: Path) -> None:
    snap = tmp_path / "sessions.snap"
    a = _replica(small_map, session_store="memory", session_snapshot=snap)
    ref = _replica(small_map)
    for svc in (a, ref):
        svc.put_session("snap", _config())
    for k in range(3):
        assert _frame(a, "snap", frames[k], k) == _frame(ref, "snap", frames[k], k)
    a.close()
    assert snap.exists()
    b = _replica(small_map, session_store="memory", session_snapshot=snap)
    assert not snap.exists()  # read once: a later crash cannot roll sessions back to it
    for k in range(3, 6):
        assert _frame(b, "snap", frames[k], k) == _frame(ref, "snap", frames[k], k)


def test_a_corrupt_snapshot_is_set_aside(small_map, frames, tmp_path: Path) -> None:
    snap = tmp_path / "sessions.snap"
    a = _replica(small_map, session_store="memory", session_snapshot=snap)
    a.put_session("c", _config())
    a.close()
    data = bytearray(snap.read_bytes())
    data[-3] ^= 0xFF
    snap.write_bytes(bytes(data))
    b = _replica(small_map, session_store="memory", session_snapshot=snap)
    assert b.sessions() == []
    assert not snap.exists() and snap.with_name("sessions.snap.corrupt").exists()


def test_sigterm_writes_the_snapshot_the_next_start_reads(tmp_path: Path, small_map,
                                                         frames) -> None:
    maps = tmp_path / "maps"
    maps.mkdir()
    save_map(small_map, maps / "small")
    snap = tmp_path / "state" / "sessions.snap"
    env = {"SWARMLOC_MAPS_DIR": str(maps), "SWARMLOC_ZENOH_ENABLED": "false",
           "SWARMLOC_SESSION_STORE": "memory", "SWARMLOC_SESSION_SNAPSHOT": str(snap)}
    ref = _replica(small_map)
    ref.put_session("t", _config())
    proc = ServiceProcess("snapshot", env, tmp_path).start().wait_ready()
    url = proc.url

    def post(k: int) -> dict[str, Any]:
        r = httpx.post(f"{url}/sessions/t/frames", params={"t": float(k), "seq": k},
                       content=frames[k], headers={"Content-Type": "image/png"}, timeout=60)
        assert r.status_code == 200, r.text
        return r.json()

    assert httpx.put(f"{url}/sessions/t", json=json.loads(_config().model_dump_json()),
                     timeout=30).status_code == 201
    for k in range(3):
        assert post(k) == json.loads(ref.process_frame(
            "t", frames[k], content_type="image/png",
            t=float(k), input_seq=k).model_dump_json())
    assert proc.stop(signal.SIGTERM) in (0, -signal.SIGTERM)  # uvicorn re-raises SIGTERM
    assert snap.exists()
    proc.start().wait_ready()
    url = proc.url
    try:
        for k in range(3, 5):
            assert post(k) == json.loads(ref.process_frame(
                "t", frames[k], content_type="image/png",
            t=float(k), input_seq=k).model_dump_json())
        assert httpx.get(f"{url}/sessions/t", timeout=30).json()["frames"] == 5
    finally:
        proc.stop()
