"""The default session store: a SQLite file (service/engine/sqlite_store.py).

Unit tests on a real file through ``LocalizationService`` (restart, corrupt rows and files,
map versions, limits, expiry, compare-and-set), and a real ``swarmloc serve`` with the
default store killed with SIGKILL mid-stream: every robot resumes bit for bit.
"""

from __future__ import annotations

import contextlib
import json
import signal
import sqlite3
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import pytest

from client.lab.processes import ServiceProcess
from service.api.errors import Conflict, NotFound, Unavailable, UnreadableSession
from service.api.models import SessionConfig
from service.engine.localization_service import LocalizationService
from service.engine.sqlite_store import SessionStoreError, sqlite_location, sqlite_url
from service.maps.route_map import RouteMap, load_map, save_map
from service.settings import Settings
from tests.test_store import _frame

SEED = 5


def _config() -> SessionConfig:
    return SessionConfig(map="small", seed=SEED)
ROBOTS = ("k1", "k2")


@pytest.fixture(scope="module")
def frames(sunny2) -> list[bytes]:
    return [sunny2.image_path(i).read_bytes() for i in range(4, 12)]


def _svc(small_map: RouteMap, db: Path | None, **settings: Any) -> LocalizationService:
    store = sqlite_url(db) if db is not None else "memory"
    return LocalizationService(Settings(zenoh_enabled=False, session_store=store, **settings),
                               maps={small_map.name: small_map})




def _rows(db: Path) -> dict[str, int]:
    with contextlib.closing(sqlite3.connect(db)) as c:
        return dict(c.execute("SELECT robot_id, version FROM sessions").fetchall())


def test_the_default_is_a_sqlite_file_in_the_maps_directory(tmp_path: Path) -> None:
    assert Settings.model_fields["session_store"].default == "sqlite"
    assert sqlite_location("sqlite", tmp_path) == (tmp_path / "sessions.sqlite", "NORMAL")
    assert sqlite_location("sqlite:///rel/s.db", tmp_path) == (Path("rel/s.db"), "NORMAL")
    assert sqlite_location("sqlite:////abs/s.db?synchronous=full", tmp_path) == \
        (Path("/abs/s.db"), "FULL")
    assert sqlite_location(sqlite_url(tmp_path / "x.db"), tmp_path)[0] == tmp_path / "x.db"
    for bad in ("sqlite://host/x.db", "sqlite:///x.db?synchronous=off", "sqlite:///x?a=1",
                "sqlite:///"):
        with pytest.raises(ValueError, match="SWARMLOC_SESSION_STORE"):
            sqlite_location(bad, tmp_path)


def test_a_restart_resumes_every_robot_bit_for_bit(small_map, frames, tmp_path: Path) -> None:
    db = tmp_path / "s.sqlite"
    a, ref = _svc(small_map, db), _svc(small_map, None)
    for svc in (a, ref):
        for r in ROBOTS:
            svc.put_session(r, _config())
    for k in range(3):
        for r in ROBOTS:
            assert _frame(a, r, frames[k], k) == _frame(ref, r, frames[k], k)
    assert sorted(a.store.ids()) == sorted(ROBOTS)
    a.close()
    assert sorted(_rows(db)) == sorted(ROBOTS)
    b = _svc(small_map, db)
    assert sorted(s.robot_id for s in b.sessions()) == sorted(ROBOTS)
    assert b.session("k1").localizer.seq == 3
    for k in range(3, 6):
        for r in ROBOTS:
            assert _frame(b, r, frames[k], k) == _frame(ref, r, frames[k], k)
    b.delete_session("k2")
    b.reset_session("k1")
    ref.reset_session("k1")
    b.close()
    c = _svc(small_map, db)  # create, reset and delete are kept too
    assert [s.robot_id for s in c.sessions()] == ["k1"]
    assert c.session("k1").localizer.seq == ref.session("k1").localizer.seq
    assert _frame(c, "k1", frames[6], 6) == _frame(ref, "k1", frames[6], 6)
    c.close()


def test_a_corrupt_row_is_refused_and_the_others_are_served(small_map, frames,
                                                            tmp_path: Path) -> None:
    db = tmp_path / "s.sqlite"
    a, ref = _svc(small_map, db), _svc(small_map, None)
    for svc in (a, ref):
        for r in ROBOTS:
            svc.put_session(r, _config())
            _frame(svc, r, frames[0], 0)
    a.close()
    with contextlib.closing(sqlite3.connect(db)) as c, c:  # closed: it would hold the file
        blob = bytearray(c.execute("SELECT state FROM sessions WHERE robot_id = 'k1'"
                                   ).fetchone()[0])
        blob[-5] ^= 0xFF
        c.execute("UPDATE sessions SET state = ? WHERE robot_id = 'k1'", (bytes(blob),))
    b = _svc(small_map, db)
    with pytest.raises(UnreadableSession, match="robot 'k1' cannot be continued"):
        _frame(b, "k1", frames[1], 1)
    with pytest.raises(UnreadableSession):
        b.session("k1")
    assert _frame(b, "k2", frames[1], 1) == _frame(ref, "k2", frames[1], 1)
    assert [s.robot_id for s in b.sessions()] == ["k2"]  # the listing serves everyone else
    b.put_session("k1", _config())  # starting it over replaces the unreadable row
    ref.put_session("k1", _config())
    assert _frame(b, "k1", frames[1], 1) == _frame(ref, "k1", frames[1], 1)
    b.close()


def test_a_corrupt_or_foreign_file_stops_the_start_with_the_reason(small_map,
                                                                   tmp_path: Path) -> None:
    junk = tmp_path / "junk.sqlite"
    junk.write_bytes(b"not a database at all, " * 200)
    before = junk.read_bytes()
    with pytest.raises(SessionStoreError, match=r"junk\.sqlite is not a readable swarmloc "
                       "session store"):
        _svc(small_map, junk)
    assert junk.read_bytes() == before
    foreign = tmp_path / "foreign.sqlite"
    with contextlib.closing(sqlite3.connect(foreign)) as c:
        c.execute("CREATE TABLE invoices (id INTEGER)")
    with pytest.raises(SessionStoreError, match=r"database of something else \(tables: "
                       "invoices"):
        _svc(small_map, foreign)
    with contextlib.closing(sqlite3.connect(foreign)) as c:
        assert c.execute("SELECT name FROM sqlite_master").fetchall() == [("invoices",)]


def test_one_process_at_a_time(small_map, tmp_path: Path) -> None:
    db = tmp_path / "s.sqlite"
    a = _svc(small_map, db)
    with pytest.raises(SessionStoreError, match="in use by another process"):
        _svc(small_map, db)
    a.close()
    _svc(small_map, db).close()  # released at close (and by the OS when a process dies)


def test_a_replaced_map_version_asks_for_a_reset(small_map, frames, tmp_path: Path) -> None:
    db = tmp_path / "s.sqlite"
    a = _svc(small_map, db)
    a.put_session("mv", _config())
    _frame(a, "mv", frames[0], 0)
    a.close()
    other = load_map(save_map(small_map, tmp_path / "small"))
    other.meta["checksum"] = "f" * 64  # as if the map had been rebuilt and replaced
    b = LocalizationService(Settings(zenoh_enabled=False, session_store=sqlite_url(db)),
                            maps={"small": other})
    with pytest.raises(Conflict, match="reset the session"):
        _frame(b, "mv", frames[1], 1)
    assert b.session("mv").map_changed  # readable, on its old version
    info = b.reset_session("mv", None)
    assert info.map_checksum == "f" * 64
    assert _frame(b, "mv", frames[1], 1)["seq"] == 1
    b.close()
    c = LocalizationService(Settings(zenoh_enabled=False, session_store=sqlite_url(db)),
                            maps={"small": other})
    assert c.session("mv").localizer.map.meta["checksum"] == "f" * 64
    c.close()


def test_limit_and_expiry_as_in_memory(small_map, tmp_path: Path) -> None:
    db = tmp_path / "s.sqlite"
    a = _svc(small_map, db, max_sessions=2, session_idle_s=60)
    a.put_session("r1", _config())
    a.put_session("r2", _config())
    with pytest.raises(Unavailable, match="session limit of 2"):
        a.put_session("r3", _config())
    assert a.put_session("r1", _config())[1] is False  # replacing one is not a new one
    a.close()
    b = _svc(small_map, db, max_sessions=2, session_idle_s=60)
    with pytest.raises(Unavailable, match="session limit of 2"):  # the limit holds on restart
        b.put_session("r3", _config())
    assert b.expire_idle(time.time() + 30) == []
    assert sorted(b.expire_idle(time.time() + 120)) == ["r1", "r2"]
    with pytest.raises(NotFound):
        b.session("r1")
    b.put_session("r3", _config())
    b.close()
    assert list(_rows(db)) == ["r3"]


def test_a_frame_on_a_replaced_session_is_not_written(small_map, frames,
                                                      tmp_path: Path) -> None:
    """Compare-and-set: a frame still running when its session is replaced (or deleted) is
    refused, and never written over the new session."""
    db = tmp_path / "s.sqlite"
    a, ref = _svc(small_map, db), _svc(small_map, None)
    for svc in (a, ref):
        svc.put_session("cas", _config())
    with pytest.raises(Conflict, match="replaced or deleted meanwhile"):
        with a.store.locked("cas") as s:
            s.localizer.seq += 100  # the old session's change, never to be seen
            a.put_session("cas", _config())
    assert a.session("cas").localizer.seq == 0
    assert _frame(a, "cas", frames[0], 0) == _frame(ref, "cas", frames[0], 0)
    with pytest.raises(Conflict):
        with a.store.locked("cas"):
            a.delete_session("cas")
    assert "cas" not in a.store.ids()
    a.close()
    assert "cas" not in _rows(db)


def test_a_failed_frame_leaves_the_stored_state(small_map, frames, tmp_path: Path) -> None:
    db = tmp_path / "s.sqlite"
    a, ref = _svc(small_map, db), _svc(small_map, None)
    for svc in (a, ref):
        svc.put_session("f", _config())
        _frame(svc, "f", frames[0], 0)
    with pytest.raises(RuntimeError):
        with a.store.locked("f") as s:
            s.localizer.seq += 100
            raise RuntimeError("the step failed half-way")
    assert _frame(a, "f", frames[1], 1) == _frame(ref, "f", frames[1], 1)
    a.close()


def test_kill_9_mid_stream_then_every_robot_resumes_bit_for_bit(tmp_path: Path, small_map,
                                                                frames) -> None:
    """A real ``swarmloc serve`` with the default store (nothing set), two robots streaming
    over HTTP, SIGKILL while both robots' next frames are in flight, a restart: the frames
    sent again and the next ones give what an uninterrupted run gives."""
    maps = tmp_path / "maps"
    maps.mkdir()
    save_map(small_map, maps / "small")
    ref = _svc(small_map, None)
    for r in ROBOTS:
        ref.put_session(r, _config())
    expected = [{r: json.loads(ref.process_frame(
        r, frames[k], content_type="image/png", t=float(k), input_seq=k).model_dump_json())
        for r in ROBOTS} for k in range(6)]
    proc = ServiceProcess("durable", {"SWARMLOC_MAPS_DIR": str(maps),
                                      "SWARMLOC_ZENOH_ENABLED": "false"}, tmp_path)
    proc.env.pop("SWARMLOC_SESSION_STORE", None)  # the default store
    proc.env.pop("SWARMLOC_SESSION_SNAPSHOT", None)

    def post(r: str, k: int) -> dict[str, Any]:
        res = httpx.post(f"{proc.url}/sessions/{r}/frames", params={"t": float(k), "seq": k},
                         content=frames[k], headers={"Content-Type": "image/png"}, timeout=60)
        assert res.status_code == 200, res.text
        return res.json()

    def frames_of(r: str) -> int:
        res = httpx.get(f"{proc.url}/sessions/{r}", timeout=30)
        assert res.status_code == 200, res.text  # the memory store fails here: no session
        return int(res.json()["frames"])

    proc.start().wait_ready()
    try:
        for r in ROBOTS:
            assert httpx.put(f"{proc.url}/sessions/{r}", timeout=30,
                             json=json.loads(_config().model_dump_json())).status_code == 201
        for k in range(3):
            for r in ROBOTS:
                assert post(r, k) == expected[k][r]
        assert (maps / "sessions.sqlite").exists()
        in_flight = [threading.Thread(target=lambda r=r: _quietly(post, r, 3))
                     for r in ROBOTS]
        for t in in_flight:
            t.start()
        time.sleep(0.05)
        assert proc.stop(signal.SIGKILL) == -signal.SIGKILL
        for t in in_flight:
            t.join()
        proc.start().wait_ready()
        for r in ROBOTS:  # at frame 3 (it was applied) or 2 (it was not): never in between
            assert frames_of(r) in (3, 4)
        for k in range(3, 6):  # frame 3 again (a retry), then the next ones
            for r in ROBOTS:
                assert post(r, k) == expected[k][r]
        for r in ROBOTS:
            assert frames_of(r) == 6
    finally:
        proc.stop(signal.SIGKILL)


def _quietly(fn: Any, *args: Any) -> None:
    """An in-flight request whose server is killed: its outcome is unknown by design."""
    try:
        fn(*args)
    except (httpx.HTTPError, AssertionError):
        pass
