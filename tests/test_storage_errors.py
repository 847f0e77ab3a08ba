"""A maps directory the service cannot write: every map write answers a JSON error naming the
map (503 read-only or not permitted, 507 full) and leaves the map and every session as they
were; an unexpected failure of any route answers a JSON 500. Over a real uvicorn server, on
real directories made unwritable for real (``MapsDir``)."""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
import zenoh

from client.dataset import Round
from service.engine.localization_service import LocalizationService
from service.maps.experiences import NewImage, add_experience
from service.maps.route_map import RouteMap, load_map
from service.server import free_port, running_server
from service.settings import Settings
from service.vision.features import extract
from service.zenoh.config import zenoh_config

PNG = {"content-type": "image/png"}
MAP = {"content-type": "application/octet-stream"}


class MapsDir:
    """A maps directory a test can make unwritable for real. As root (whom file permissions
    do not stop) a tmpfs is mounted on it: remounted read-only (EROFS) or filled up
    (ENOSPC); otherwise its write permission is taken away (EACCES). Where neither works
    (root without the right to mount) the test is skipped."""

    def __init__(self, path: Path) -> None:
        self.path = path
        path.mkdir()
        self.mounted = False
        if os.geteuid() == 0:
            done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=96m", "swarmloc-test",
                                   str(path)], capture_output=True, text=True, check=False)
            if done.returncode != 0:
                pytest.skip("root without the right to mount a tmpfs: no real way to make "
                            f"a directory unwritable here ({done.stderr.strip()})")
            self.mounted = True

    def _remount(self, mode: str) -> None:
        subprocess.run(["mount", "-o", f"remount,{mode}", str(self.path)], check=True)

    @contextlib.contextmanager
    def read_only(self) -> Iterator[None]:
        if self.mounted:
            self._remount("ro")
        else:
            self.path.chmod(0o555)
        try:
            yield
        finally:
            if self.mounted:
                self._remount("rw")
            else:
                self.path.chmod(0o755)

    @contextlib.contextmanager
    def full(self) -> Iterator[None]:
        if not self.mounted:
            pytest.skip("a full filesystem needs a tmpfs of its own (root)")
        filler = self.path / "filler.bin"  # not hidden, not .swmap: never taken for a map
        fd = os.open(filler, os.O_WRONLY | os.O_CREAT, 0o644)
        try:
            for size in (1 << 20, 4096):  # to the last page
                with contextlib.suppress(OSError):
                    while True:
                        os.write(fd, bytes(size))
            with pytest.raises(OSError) as exc:
                os.write(fd, b"x")
            assert exc.value.errno == errno.ENOSPC
        finally:
            os.close(fd)
        try:
            yield
        finally:
            filler.unlink()

    def close(self) -> None:
        if self.mounted:  # lazily: a closed service's maps may still be memory-mapped
            subprocess.run(["umount", "-l", str(self.path)], check=False)


@pytest.fixture
def maps_dir(tmp_path: Path) -> Iterator[MapsDir]:
    d = MapsDir(tmp_path / "maps")
    yield d
    d.close()


def _map_with_experience(small_map: RouteMap, cloudy1: Round, directory: Path) -> None:
    """The small map in ``directory`` with one learned experience, 'e1'."""
    assert small_map.path is not None
    shutil.copy(small_map.path, directory / "small.swmap")
    m = load_map(directory / "small.swmap")
    images = [NewImage(f.codes, f.keypoints, np.asarray(cloudy1.xy[i], float), f"cloudy/{i}")
              for i, f in enumerate(extract(cloudy1.load_image(i), m.feature_params)
                                    for i in range(10))]
    assert m.path is not None
    add_experience(m, m.path, "e1", images, condition="cloudy", robot="r1", now=1.0e9,
                   budget_bytes=1 << 30)


@contextlib.contextmanager
def _serving_a_map_with_experience(maps_dir: MapsDir, small_map: RouteMap, cloudy1: Round
                                   ) -> Iterator[tuple[httpx.Client, bytes]]:
    """A real server on ``maps_dir`` with map ``small`` (experience ``e1``) and robot
    ``walker`` on it: its HTTP client and the map file's bytes (an upload to send back)."""
    _map_with_experience(small_map, cloudy1, maps_dir.path)
    upload = (maps_dir.path / "small.swmap").read_bytes()
    service = _service(maps_dir.path)
    try:
        with running_server(service, zenoh=False) as url, \
                httpx.Client(base_url=url, timeout=60) as http:
            assert http.put("/sessions/walker", json={"map": "small"}).status_code == 201
            yield http, upload
    finally:
        service.close()


def _service(maps: Path, **kw: object) -> LocalizationService:
    return LocalizationService(Settings(maps_dir=maps, host="127.0.0.1", port=free_port(),
                                        session_store="memory", **kw))


def _state(http: httpx.Client) -> tuple[str, list[str], list[tuple[str, str, int]]]:
    """The map's version and experiences, and every session (robot, map version, frames)."""
    got = http.get("/maps/small")
    assert got.status_code == 200, got.text
    sessions = http.get("/sessions").json()
    return (got.headers["ETag"], [e["id"] for e in got.json()["experiences"]],
            sorted((s["robot_id"], s["map_checksum"], s["frames"]) for s in sessions))


def _json_error(r: httpx.Response, status: int, *words: str) -> str:
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == "application/json", r.text
    body = r.json()
    assert set(body) <= {"error", "detail"}, body
    err = body["error"]
    assert "Traceback" not in err and all(w in err for w in words), err
    return err


def test_map_writes_into_a_read_only_maps_directory_answer_503_and_change_nothing(
        maps_dir: MapsDir, small_map: RouteMap, cloudy1: Round, sunny2: Round) -> None:
    """Regression: DELETE /maps/{name}/experiences/{id}, PUT /maps/{name}, DELETE
    /maps/{name} and POST /maps/{name}/build on a maps directory the service may not write
    answered a plain-text 500 (an OSError nobody handled; a map delete had already ended its
    sessions and dropped the map when the file's removal failed)."""
    with _serving_a_map_with_experience(maps_dir, small_map, cloudy1) as (http, upload):
        assert http.post("/sessions/walker/frames", params={"t": 0.0}, headers=PNG,
                         content=sunny2.image_path(0).read_bytes()).status_code == 200
        before = _state(http)
        assert before[1] == ["e1"]
        with maps_dir.read_only():
            for method, path, body, headers in (
                    ("DELETE", "/maps/small/experiences/e1", None, {}),
                    ("PUT", "/maps/small", upload, MAP),
                    ("DELETE", "/maps/small?force=true", None, {}),
                    ("POST", "/maps/small/build", b"PK\x03\x04" + bytes(100),
                     {"content-type": "application/zip"})):
                r = http.request(method, path, content=body, headers=headers)
                err = _json_error(r, 503, "map 'small'", "maps directory is not writable",
                                  "unchanged")
                assert str(maps_dir.path) not in err, err
                assert _state(http) == before, (method, path)
            assert http.post("/sessions/walker/frames", params={"t": 1.0}, headers=PNG,
                             content=sunny2.image_path(1).read_bytes()).status_code == 200
        assert not [p.name for p in maps_dir.path.iterdir() if p.name.startswith(".swarmloc")]
        r = http.delete("/maps/small/experiences/e1")  # writable again: the same request
        assert r.status_code == 200 and r.json()["experiences"] == [], r.text


def test_map_writes_on_a_full_disk_answer_507_and_change_nothing(
        maps_dir: MapsDir, small_map: RouteMap, cloudy1: Round) -> None:
    """Regression: as above on a full disk (ENOSPC): a plain-text 500."""
    with _serving_a_map_with_experience(maps_dir, small_map, cloudy1) as (http, upload):
        before = _state(http)
        with maps_dir.full():
            for method, path, body, headers in (
                    ("DELETE", "/maps/small/experiences/e1", None, {}),
                    ("PUT", "/maps/small", upload, MAP),
                    ("POST", "/maps/small/build", b"PK\x03\x04" + bytes(100),
                     {"content-type": "application/zip"})):
                r = http.request(method, path, content=body, headers=headers)
                _json_error(r, 507, "map 'small'", "no space left", "unchanged")
                assert _state(http) == before, (method, path)
        assert not [p.name for p in maps_dir.path.iterdir() if p.name.startswith(".swarmloc")]


class _Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def test_an_unexpected_failure_of_a_route_is_a_json_500_logged_once(
        tmp_path: Path, small_map: RouteMap) -> None:
    """Regression: an exception no handler knew (here the map's file removed by hand behind
    the service's back, then downloaded) answered uvicorn's plain-text 500."""
    assert small_map.path is not None
    shutil.copy(small_map.path, tmp_path / "small.swmap")
    service = _service(tmp_path)
    seen = _Records()
    loggers = [logging.getLogger(n) for n in ("swarmloc", "uvicorn")]
    for lg in loggers:
        lg.addHandler(seen)
    try:
        with running_server(service, zenoh=False) as url, \
                httpx.Client(base_url=url, timeout=60) as http:
            (tmp_path / "small.swmap").unlink()
            r = http.get("/maps/small/file")
            err = _json_error(r, 500, "internal error; see the service log")
            assert str(tmp_path) not in err
            assert http.get("/healthz").status_code == 200  # the service goes on
    finally:
        for lg in loggers:
            lg.removeHandler(seen)
    tracebacks = [rec for rec in seen.records if rec.exc_info]
    assert len(tracebacks) == 1, [rec.getMessage() for rec in tracebacks]
    assert tracebacks[0].exc_info is not None
    assert tracebacks[0].exc_info[0] is FileNotFoundError
    assert "GET /maps/small/file" in tracebacks[0].getMessage()
    service.close()


def test_a_learning_session_is_refused_where_its_map_cannot_be_written(
        maps_dir: MapsDir, small_map: RouteMap) -> None:
    """Regression: a session with "learn": true on a maps directory the service cannot write
    was accepted (HTTP and Zenoh control), and each batch it learned then failed into the
    log. Now it is refused at creation (503), over both transports alike; a session that only
    localizes is served as ever."""
    assert small_map.path is not None
    shutil.copy(small_map.path, maps_dir.path / "small.swmap")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    service = _service(maps_dir.path, zenoh_listen=[endpoint], zenoh_multicast_scouting=False)
    learn = {"map": "small", "learn": True}

    def control(peer: zenoh.Session, robot: str, body: dict) -> dict:
        (reply,) = peer.get(f"swarmloc/{robot}/control", payload=json.dumps(body).encode(),
                            timeout=20)
        if reply.err is not None:
            return {"ok": False, **json.loads(reply.err.payload.to_bytes())}
        return {"ok": True, **json.loads(reply.ok.payload.to_bytes())}

    with running_server(service) as url, httpx.Client(base_url=url, timeout=60) as http:
        peer = zenoh.open(zenoh_config(mode="peer", connect=[endpoint]))
        try:
            time.sleep(0.5)  # let the peers connect before the first query
            assert http.put("/sessions/walker", json={"map": "small"}).status_code == 201
            with maps_dir.read_only():
                r = http.put("/sessions/teacher", json=learn)
                err = _json_error(r, 503, "map 'small' cannot learn",
                                  "maps directory is not writable", "without learn")
                assert str(maps_dir.path) not in err
                got = control(peer, "zteacher", {"action": "put", **learn})
                assert (got["ok"], got["status"], got["error"]) == (False, 503, err)
                r = http.put("/sessions/walker", json=learn)  # a running session asks to learn
                _json_error(r, 503, "cannot learn")
                # sessions that only localize are created (and the refused ones were not)
                assert http.put("/sessions/second", json={"map": "small"}).status_code == 201
                assert control(peer, "zsecond", {"action": "put", "map": "small"})["ok"]
                assert sorted(s["robot_id"] for s in http.get("/sessions").json()) == \
                    ["second", "walker", "zsecond"]
                assert http.get("/sessions/walker").json()["learn"] is False
            # writable again: the same requests are accepted
            assert http.put("/sessions/teacher", json=learn).status_code == 201
            assert control(peer, "zteacher", {"action": "put", **learn})["learn"] is True
        finally:
            peer.close()
    assert not [p.name for p in maps_dir.path.iterdir() if p.name.startswith(".swarmloc")]
    service.close()
