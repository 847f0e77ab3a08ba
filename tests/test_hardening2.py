"""Issue 30's defects (hardening, round two), one regression test each, against the shared
real server of tests/conftest.py (uvicorn and a Zenoh bridge on loopback). Each of these
failed on the code before the fix."""

from __future__ import annotations

import io
import json
import logging
import socket
import tarfile
import threading
import time
import zlib
from collections.abc import Iterator
from http.client import HTTPConnection
from pathlib import Path
from urllib.parse import urlsplit

import httpx
import numpy as np
import pytest
import zenoh

from service.api.errors import ServiceError
from service.engine.localization_service import LocalizationService
from service.maps.route_map import MapError, load_map, save_map
from service.server import build_app, free_port, running_server
from service.settings import Settings
from service.zenoh.config import ZenohSecurityError, check_security, zenoh_config
from tests.test_fuzz_parsers import _tar_header
from tests.test_hardening import _write_map

PNG = {"content-type": "image/png"}
TGZ = {"content-type": "application/gzip"}


@pytest.fixture(scope="module")
def http(server) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server["url"], timeout=120) as c:
        yield c


@pytest.fixture(scope="module")
def peer(server) -> Iterator[zenoh.Session]:
    s = zenoh.open(zenoh_config(mode="peer", connect=[server["zenoh"]]))
    time.sleep(0.5)  # let the peers connect before the first query
    yield s
    s.close()


def _fresh(http: httpx.Client, robot: str) -> None:
    r = http.put(f"/sessions/{robot}", json={"map": "small", "seed": 1})
    assert r.status_code in (200, 201), r.text


def _rss_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


# ---- tar records made by hand (tarfile would not write these) -----------------------------
def _meta_tar(kind: bytes, size: int, fill: bytes = b"1") -> Iterator[bytes]:
    """A tar (in chunks) with one ``kind`` record of ``size`` bytes of ``fill``, one file."""
    yield _tar_header(b"././@LongLink", size, kind)
    left = size
    while left:
        n = min(left, 1 << 20)
        yield fill * n
        left -= n
    yield b"\x00" * (-size % 512) + _tar_header(b"a.txt", 0, b"0") + b"\x00" * 1024


def _tgz(chunks: Iterator[bytes]) -> bytes:
    z = zlib.compressobj(9, zlib.DEFLATED, 31)  # gzip framing
    return b"".join(z.compress(c) for c in chunks) + z.flush()


BOMBS = {
    "pax-150k-digits": lambda: _tgz(_meta_tar(b"x", 150_000)),  # CVE-2024-6232: 297 bytes
    "pax-1GiB": lambda: _tgz(_meta_tar(b"x", 1 << 30, b"\x00")),  # ~1 MB, memory
    "gnu-longname-10MB": lambda: _tgz(_meta_tar(b"L", 10_000_000, b"a")),  # the echoed name
}


# ---- 1 + 2. tar headers are bounded before tarfile parses them ----------------------------
@pytest.mark.parametrize("bomb", sorted(BOMBS))
def test_tar_header_bombs_get_a_bounded_413(server, http, bomb) -> None:
    data = BOMBS[bomb]()
    assert len(data) < 2_000_000
    peak = [_rss_mib()]
    base = peak[0]
    stop = threading.Event()

    def sample() -> None:
        while not stop.is_set():
            peak[0] = max(peak[0], _rss_mib())
            time.sleep(0.02)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    try:
        r = http.post(f"/maps/bomb-{bomb}/build", content=data, headers=TGZ)
    finally:
        stop.set()
        sampler.join()
    print(f"{bomb}: {len(data)} bytes, answer {r.status_code} in {r.elapsed.total_seconds():.3f}"
          f" s, RSS +{peak[0] - base:.0f} MiB")
    assert r.status_code == 413, r.text[:300]
    assert len(r.content) < 1000 and "limit is 8192 bytes" in r.json()["error"]
    assert peak[0] - base < 300  # the 1 GiB header is never read
    assert http.get("/healthz").status_code == 200
    assert not [p for p in Path(server["maps"]).iterdir() if p.name.startswith(".swarmloc-")]


def test_tar_header_bomb_over_zenoh_maps_is_a_413(peer) -> None:
    replies = list(peer.get("swarmloc/@maps/zbomb", payload=BOMBS["pax-150k-digits"](),
                            attachment=json.dumps({"action": "build"}).encode(), timeout=60))
    assert len(replies) == 1 and replies[0].err is not None
    err = json.loads(replies[0].err.payload.to_bytes())
    assert err["status"] == 413 and "pax header" in err["error"]


def test_a_pax_header_of_many_digit_runs_is_refused(tmp_path: Path) -> None:
    """Under the size bound, digits in a row are what the quadratic regex costs."""
    from service.maps.round_archive import ArchiveLimits, extract_round

    path = tmp_path / "digits.tgz"
    path.write_bytes(_tgz(_meta_tar(b"x", 4000)))
    with pytest.raises(ServiceError, match="digits in a row") as exc:
        extract_round(path, tmp_path / "out", ArchiveLimits())
    assert exc.value.status == 400


# ---- 3. positions beyond the pose bound ---------------------------------------------------
def _round_tgz(rounds_dir: Path, x0: str) -> bytes:
    src = rounds_dir / "sunny1"
    lines = (src / "poses.csv").read_text().splitlines()
    header, rows = lines[0], lines[1:4]
    cols = header.split(",")
    first = rows[0].split(",")
    first[cols.index("x")] = x0
    rows[0] = ",".join(first)
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        csv = "\n".join([header, *rows]).encode()
        info = tarfile.TarInfo("round/poses.csv")
        info.size = len(csv)
        tf.addfile(info, io.BytesIO(csv))
        for row in rows:
            name = row.split(",")[cols.index("image")]
            tf.add(src / name, f"round/{name}")
    return buf.getvalue()


def test_a_round_beyond_the_pose_bound_is_refused_at_upload(http, rounds_dir) -> None:
    r = http.post("/maps/far/build", content=_round_tgz(rounds_dir, "1e300"), headers=TGZ)
    assert r.status_code == 422 and "beyond" in r.json()["error"], r.text[:300]
    assert http.get("/maps/far").status_code == 404


def test_a_map_with_unusable_positions_does_not_load(tmp_path: Path, small_map) -> None:
    pos = np.array(small_map.positions, float)
    pos[2, 0] = 1e300
    _write_map(small_map, tmp_path / "far", name="far", positions=pos)
    with pytest.raises(MapError, match="estimators cannot use them"):
        load_map(tmp_path / "far.swmap")


# ---- 4. Zenoh localize queries are bounded: newest wins -----------------------------------
def test_zenoh_localize_queries_do_not_queue(server, http, peer, sunny2) -> None:
    _fresh(http, "zq")
    frame = sunny2.image_path(3).read_bytes()
    handlers = [peer.get("swarmloc/zq/localize", payload=frame, timeout=60,
                         attachment=json.dumps({"seq": k}).encode()) for k in range(24)]
    statuses = []
    for h in handlers:
        replies = list(h)
        assert len(replies) == 1
        rep = replies[0]
        statuses.append(200 if rep.ok is not None else
                        json.loads(rep.err.payload.to_bytes())["status"])
    assert set(statuses) <= {200, 429} and statuses[-1] == 200
    assert statuses.count(429) > 0  # the waiting queries were replaced, not queued
    assert http.get("/sessions/zq").json()["frames"] == statuses.count(200)


# ---- 5. the start-up check reads the Zenoh config file ------------------------------------
def _json5(path: Path, cfg: dict) -> Path:
    path.write_text(json.dumps(cfg))
    return path


def test_a_zenoh_config_without_auth_is_refused_with_a_token(tmp_path: Path) -> None:
    listen = {"endpoints": [f"tcp/127.0.0.1:{free_port()}"]}
    bare = _json5(tmp_path / "bare.json5", {"scouting": {"multicast": {"enabled": False}},
                                            "listen": listen})
    with pytest.raises(ZenohSecurityError) as exc:
        build_app(Settings(maps_dir=tmp_path, auth_token="tok", zenoh_config_file=bare))
    msg = str(exc.value)
    assert "\n" not in msg and "--no-zenoh" in msg and "transport.auth.usrpwd" in msg
    mtls_on_tcp = _json5(tmp_path / "tcp.json5", {"listen": listen, "transport": {
        "link": {"tls": {"enable_mtls": True}}}})
    with pytest.raises(ZenohSecurityError):
        check_security(Settings(maps_dir=tmp_path, auth_token="tok",
                                zenoh_config_file=mtls_on_tcp))
    (tmp_path / "users.txt").write_text("robot1:secret\n")
    for good in ({"transport": {"auth": {"usrpwd": {
                     "dictionary_file": str(tmp_path / "users.txt")}}}},
                 {"access_control": {"enabled": True, "default_permission": "deny"}}):
        cfg = _json5(tmp_path / "good.json5", {"listen": listen, **good})
        check_security(Settings(maps_dir=tmp_path, auth_token="tok", zenoh_config_file=cfg))


# ---- 6. timestamps are bounded ------------------------------------------------------------
@pytest.mark.parametrize("bad_t", [1e300, 2.0**31 - 1])
def test_a_far_timestamp_is_refused_and_the_robot_keeps_going(http, sunny2, bad_t) -> None:
    _fresh(http, "clock")
    frame = sunny2.image_path(3).read_bytes()
    assert http.post("/sessions/clock/frames", params={"t": 100.0}, content=frame,
                     headers=PNG).status_code == 200
    r = http.post("/sessions/clock/frames", params={"t": bad_t}, content=frame, headers=PNG)
    assert r.status_code == 422 and "timestamp" in r.json()["error"]
    assert http.get("/sessions/clock").json()["frames"] == 1
    ok = http.post("/sessions/clock/frames", params={"t": 101.0}, content=frame, headers=PNG)
    assert ok.status_code == 200 and ok.json()["seq"] == 2


# ---- 7. bad JSON on Zenoh is a 400 on every channel ---------------------------------------
BAD_JSON = [b"[" * 100_000, b'{"seq": ' + b"1" * 5000 + b"}", b"\xff{"]


def _err(replies: list) -> dict:
    assert len(replies) == 1 and replies[0].err is not None
    return json.loads(replies[0].err.payload.to_bytes())


@pytest.mark.parametrize("raw", BAD_JSON, ids=["deep", "digits", "utf8"])
def test_bad_json_on_zenoh_is_a_400(http, peer, sunny2, raw) -> None:
    frame = sunny2.image_path(3).read_bytes()
    assert _err(list(peer.get("swarmloc/zj/localize", payload=frame, attachment=raw,
                              timeout=30)))["status"] == 400
    assert _err(list(peer.get("swarmloc/zj/control", payload=raw, timeout=30)))["status"] == 400
    assert _err(list(peer.get("swarmloc/@maps/small", attachment=raw,
                              timeout=30)))["status"] == 400
    got: list[dict] = []
    sub = peer.declare_subscriber("swarmloc/zj/estimate",
                                  lambda s: got.append(json.loads(s.payload.to_bytes())))
    try:
        time.sleep(0.3)
        peer.put("swarmloc/zj/frame", frame, attachment=raw)
        for _ in range(200):
            if got:
                break
            time.sleep(0.05)
    finally:
        sub.undeclare()
    assert got and got[0]["status"] == 400


@pytest.mark.parametrize("opts", [{"if_match": 5}, {"force": "yes"}, {"action": ["get"]},
                                  {"max_features": "60"}, {"max_features": True},
                                  {"width": 320.0}])
def test_bad_map_options_on_zenoh_are_a_400(peer, opts) -> None:
    err = _err(list(peer.get("swarmloc/@maps/small", attachment=json.dumps(opts).encode(),
                             timeout=30)))
    assert err["status"] == 400 and "attachment option" in err["error"]


# ---- 8. one robot-id rule -----------------------------------------------------------------
def test_dot_robot_ids_are_refused_over_raw_http(server, http) -> None:
    u = urlsplit(server["url"])
    for rid in ("..", ".", "..."):
        conn = HTTPConnection(u.hostname, u.port, timeout=30)  # sends the path as it is
        conn.request("PUT", f"/sessions/{rid}", body=b'{"map": "small"}',
                     headers={"content-type": "application/json"})
        resp = conn.getresponse()
        body = resp.read()
        conn.close()
        assert resp.status in (404, 422), (rid, resp.status, body)
    assert not [s for s in http.get("/sessions").json() if set(s["robot_id"]) == {"."}]


def test_unicode_robot_ids_are_refused_on_zenoh_control(peer) -> None:
    for rid in ("r\u00f6bot", "\u0661\u0662"):  # letters and digits to str.isalnum
        err = _err(list(peer.get(f"swarmloc/{rid}/control",
                                 payload=json.dumps({"action": "put"}).encode(), timeout=30)))
        assert err["status"] == 422 and "robot id" in err["error"]


def test_the_robot_id_rule() -> None:
    from service.api.models import check_robot_id

    for ok in ("robot1", "a.b", "r-2_x", ".hidden", "x" * 128):
        assert check_robot_id(ok) == ok
    for bad in ("", ".", "..", "...", "r\u00f6bot", "\u0661", "a/b", "a b", "x" * 129):
        with pytest.raises(ServiceError) as exc:
            check_robot_id(bad)
        assert exc.value.status == 422


# ---- 9. ROS 2 raw images get the frame size limits -----------------------------------------
@pytest.mark.parametrize(("w", "h"), [(1, 1), (20_000, 1), (8, 200)])
def test_ros2_raw_images_need_16_px(w, h) -> None:
    pytest.importorskip("rosbags")
    from service.zenoh.ros2 import IMAGE, Codec

    codec = Codec()
    t = codec.types
    msg = t[IMAGE](header=t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="cam"),
        height=h, width=w, encoding="mono8", is_bigendian=0, step=w,
        data=np.zeros(w * h, np.uint8))
    payload = codec.serialize(msg, IMAGE)
    with pytest.raises(ServiceError, match="at least 16x16") as exc:
        codec.frame(payload, IMAGE, 1 << 26, 16_000_000, 16)
    assert exc.value.status == 400


# ---- 10. HTTP head size and read timeouts -------------------------------------------------
def test_a_50_kb_header_line_gets_431(server) -> None:
    u = urlsplit(server["url"])
    with socket.create_connection((u.hostname, u.port), timeout=30) as s:
        s.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Big: " + b"a" * 50_000 + b"\r\n\r\n")
        answer = s.recv(4096)
    assert answer.startswith(b"HTTP/1.1 431"), answer[:100]
    assert httpx.get(server["url"] + "/healthz").status_code == 200


@pytest.fixture(scope="module")
def quick(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict]:
    """A server with a 1 s read timeout (and no maps: only the transport is tested)."""
    maps = tmp_path_factory.mktemp("quick_maps")
    settings = Settings(maps_dir=maps, host="127.0.0.1", port=free_port(), workers=2,
                        zenoh_enabled=False, http_read_timeout_s=1.0)
    with running_server(LocalizationService(settings), zenoh=False) as url:
        yield {"url": url, "maps": maps}


def _closed_by_server(sock: socket.socket) -> bytes:
    """What the server sends until it closes the connection (the socket's own timeout of
    30 s fails the test if it never does)."""
    got = b""
    while chunk := sock.recv(4096):
        got += chunk
    return got


def test_a_half_sent_request_head_is_closed_after_the_read_timeout(quick) -> None:
    u = urlsplit(quick["url"])
    with socket.create_connection((u.hostname, u.port), timeout=30) as s:
        s.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")  # never finished
        assert _closed_by_server(s).startswith(b"HTTP/1.1 408")
    with socket.create_connection((u.hostname, u.port), timeout=30) as s:
        assert _closed_by_server(s).startswith(b"HTTP/1.1 408")  # connected, sent nothing


def test_a_stalled_upload_is_closed_and_leaves_no_staging_file(
        quick, caplog: pytest.LogCaptureFixture) -> None:
    u = urlsplit(quick["url"])
    with caplog.at_level(logging.WARNING):
        with socket.create_connection((u.hostname, u.port), timeout=30) as s:
            s.sendall(b"POST /maps/slow/build HTTP/1.1\r\nHost: x\r\ncontent-type: "
                      b"application/gzip\r\ncontent-length: 100000\r\n\r\n" + b"\x1f" * 1000)
            assert _closed_by_server(s) == b""
        for _ in range(100):  # the route notices the disconnect and removes its file
            if not [p for p in Path(quick["maps"]).iterdir()] and "disconnected" in caplog.text:
                break
            time.sleep(0.05)
    assert not list(Path(quick["maps"]).iterdir())
    # cosmetic: one WARNING line, no ERROR traceback
    assert [r.getMessage() for r in caplog.records if "disconnected" in r.getMessage()]
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]


# ---- cosmetic ------------------------------------------------------------------------------
def test_models_are_strict(http) -> None:
    r = http.put("/sessions/strict", json={"map": "small", "seed": True})
    assert r.status_code == 422 and "seed" in r.json()["error"]
    _fresh(http, "strict")
    r = http.post("/sessions/strict/reset", json={"x": "1", "y": 0.0})
    assert r.status_code == 422 and "x" in r.json()["error"]


def test_a_map_file_with_junk_appended_is_refused(tmp_path: Path, http, small_map) -> None:
    path = save_map(small_map, tmp_path / "small")
    data = path.read_bytes() + b"junk" * 10
    path.write_bytes(data)
    with pytest.raises(MapError, match="appended"):
        load_map(path)
    r = http.put("/maps/small", content=data,
                 headers={"content-type": "application/octet-stream"})
    assert r.status_code == 400 and "appended" in r.json()["error"]
