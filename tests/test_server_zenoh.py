"""A real uvicorn server with the Zenoh bridge on loopback, driven by the client library."""

from __future__ import annotations

import contextlib
import json
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from functools import partial

import httpx
import numpy as np
import pytest
import zenoh

from client.transports import HttpClient, LocalClient, SwarmlocError, ZenohClient
from service.api.models import Estimate, Odometry
from service.server import free_port
from service.zenoh.config import zenoh_config


def _peer(endpoint: str) -> zenoh.Session:
    return zenoh.open(zenoh_config(mode="peer", connect=[endpoint]))


def _control(peer: zenoh.Session, robot: str, body: dict) -> dict:
    """A control query's reply (it must not be an error)."""
    (reply,) = peer.get(f"swarmloc/{robot}/control", payload=json.dumps(body).encode(),
                        timeout=20)
    assert reply.ok is not None, reply.err.payload.to_bytes()
    return json.loads(reply.ok.payload.to_bytes())


def _replay(client, robot: str, rnd, frames: range, seed: int) -> list[tuple]:
    client.create_session(robot, "small", "dpso", None, seed)
    out = []
    for k, i in enumerate(frames):
        e = client.localize(robot, rnd.image_path(i).read_bytes(), t=float(k), seq=k)
        out.append((e.x, e.y, e.speed, e.comparisons, e.status))
    client.delete_session(robot)
    return out


def test_same_estimates_over_http_zenoh_and_in_process(server, sunny2) -> None:
    frames = range(5, 35)
    http = HttpClient(server["url"])
    z = ZenohClient([server["zenoh"]], mode="peer")
    local = LocalClient(server["maps"])
    try:
        via_http = _replay(http, "same", sunny2, frames, 4)
        via_zenoh = _replay(z, "same", sunny2, frames, 4)
        via_local = _replay(local, "same", sunny2, frames, 4)
    finally:
        http.close()
        z.close()
    assert via_http == via_zenoh == via_local
    errs = [np.hypot(x - sunny2.truth_xy[i, 0], y - sunny2.truth_xy[i, 1])
            for (x, y, *_), i in zip(via_http, frames, strict=True)]
    assert np.mean(errs[-10:]) < 3.0


def test_sixteen_robots_in_parallel_equal_each_alone(server, sunny2) -> None:
    robots = [(f"robot{k}", range(6 * k, 6 * k + 6), k) for k in range(16)]
    alone = {}
    c = HttpClient(server["url"])
    for rid, frames, seed in robots:
        alone[rid] = _replay(c, rid, sunny2, frames, seed)
    c.close()

    def one(args: tuple) -> tuple[str, list]:
        rid, frames, seed = args
        cl = HttpClient(server["url"])
        try:
            return rid, _replay(cl, rid, sunny2, frames, seed)
        finally:
            cl.close()

    with ThreadPoolExecutor(16) as pool:
        together = dict(pool.map(one, robots))
    assert together == alone


def test_zenoh_stream_publishes_estimates_and_drops_stale_frames(server, sunny2) -> None:
    service = server["service"]
    peer = _peer(server["zenoh"])
    got: list[dict] = []
    done = threading.Event()

    def on_estimate(sample: zenoh.Sample) -> None:
        body = json.loads(sample.payload.to_bytes())
        got.append(body)
        if body.get("input_seq") == 29:
            done.set()

    sub = peer.declare_subscriber("swarmloc/streamer/estimate", on_estimate)
    time.sleep(0.5)
    def dropped_total() -> float:
        return service.metrics.registry.get_sample_value("swarmloc_zenoh_dropped_frames_total")

    dropped_before = dropped_total()
    try:
        for k in range(30):  # a burst much faster than frames are processed
            # BLOCK: Zenoh itself must not drop frames here, only the service's stale policy
            peer.put("swarmloc/streamer/frame", sunny2.image_path(k).read_bytes(),
                     attachment=json.dumps({"t": float(k), "seq": k}).encode(),
                     congestion_control=zenoh.CongestionControl.BLOCK)
        arrived = done.wait(60)
        seen = [(g.get("input_seq"), g.get("error")) for g in got]
        assert arrived, f"the newest frame's estimate never arrived: {seen}"
    finally:
        sub.undeclare()
        peer.close()
    assert all("error" not in g for g in got)
    seqs = [g["input_seq"] for g in got]
    assert seqs == sorted(seqs) and seqs[-1] == 29
    dropped = dropped_total() - dropped_before
    assert len(got) + dropped == 30 and dropped > 0
    assert got[-1]["robot_id"] == "streamer" and got[-1]["frame_id"] == "small"


def test_zenoh_errors_carry_the_http_messages(server, sunny2) -> None:
    z = ZenohClient([server["zenoh"]], mode="peer")
    http = HttpClient(server["url"])
    try:
        z.create_session("zerr", "small")
        with pytest.raises(SwarmlocError) as ez:
            z.localize("zerr", b"junk")
        http.create_session("herr", "small")
        with pytest.raises(SwarmlocError) as eh:
            http.localize("herr", b"junk")
        assert ez.value.status == eh.value.status == 400
        assert ez.value.message == eh.value.message
        info_before = z.session("zerr")
        assert info_before.frames == 0  # the rejected frame changed nothing
        with pytest.raises(SwarmlocError) as e2:
            z.create_session("zerr", "nope")
        assert e2.value.status == 404 and "unknown map 'nope'" in e2.value.message
        with pytest.raises(SwarmlocError) as e3:
            z._control("zerr", {"action": "fly"})
        assert e3.value.status == 400
        # broken frame on the publish channel: the error comes back on the estimate key
        peer = _peer(server["zenoh"])
        got: list[dict] = []
        ev = threading.Event()
        sub = peer.declare_subscriber("swarmloc/zerr/estimate",
                                      lambda s: (got.append(json.loads(s.payload.to_bytes())),
                                                 ev.set()))
        time.sleep(0.5)
        peer.put("swarmloc/zerr/frame", b"\x89PNG\r\n\x1a\nbroken", attachment=b'{"seq": 7}')
        assert ev.wait(20)
        sub.undeclare()
        peer.close()
        assert got[0]["status"] == 400 and got[0]["input_seq"] == 7
        assert "IHDR" in got[0]["error"]
        assert z.session("zerr").frames == 0
    finally:
        z.close()
        http.close()


def test_zenoh_first_frame_creates_default_session(server, sunny2) -> None:
    z = ZenohClient([server["zenoh"]], mode="peer")
    try:
        est = z.localize("newcomer", sunny2.image_path(0).read_bytes(), t=0.0)
        assert est.seq == 1 and est.frame_id == "small"
        assert z.session("newcomer").frames == 1
        z.delete_session("newcomer")
    finally:
        z.close()


def test_metrics_count_what_happened(server) -> None:
    text = httpx.get(server["url"] + "/metrics").text
    values = {}
    for line in text.splitlines():
        if line.startswith("swarmloc_") and not line.startswith("#"):
            name, _, v = line.rpartition(" ")
            values[name] = float(v)
    assert values['swarmloc_frames_total{transport="http"}'] > 0
    assert values['swarmloc_frames_total{transport="zenoh"}'] > 0
    assert values["swarmloc_comparisons_total"] > 0
    assert values['swarmloc_frame_latency_seconds_count{transport="http"}'] == \
        values['swarmloc_frames_total{transport="http"}']
    assert values['swarmloc_rejected_inputs_total{reason="BadRequest"}'] >= 2
    assert values["swarmloc_zenoh_dropped_frames_total"] > 0
    assert values["swarmloc_maps_loaded"] == 1


def test_client_reports_unreachable_service() -> None:
    c = HttpClient(f"http://127.0.0.1:{free_port()}", retries=0, timeout=2)
    with pytest.raises(SwarmlocError) as exc:
        c.maps()
    assert exc.value.status == 0 and "cannot reach" in exc.value.message
    c.close()


def test_async_http_client(server, sunny2) -> None:
    import asyncio

    from client.transports import AsyncHttpClient

    async def go() -> tuple:
        c = AsyncHttpClient(server["url"])
        try:
            await c.create_session("async", "small", seed=2)
            e = await c.localize("async", sunny2.image_path(3).read_bytes(), t=0.0)
            await c.delete_session("async")
            return e.seq, e.comparisons
        finally:
            await c.close()

    seq, comps = asyncio.run(go())
    assert seq == 1 and comps > 0



def test_zenoh_frames_carry_odometry_and_bad_odometry_is_refused(server, sunny2) -> None:
    """``{"odom": {"x", "y", "yaw"}}`` in a frame's attachment is fused (the heading becomes
    the odometry's); a bad odom there (out of range, a 500 m jump, no yaw) gets the Zenoh
    error reply with the HTTP status and message, and the session is untouched: the next
    frame gives what a twin session that never saw the bad frames gives."""
    assert sunny2.odometry is not None
    z = ZenohClient([server["zenoh"]], mode="peer")
    frames = range(5, 30)

    def send(robot: str, k: int, i: int) -> Estimate:
        x, y, yaw = (float(v) for v in sunny2.odometry[i])
        return z.localize(robot, sunny2.image_path(i).read_bytes(), t=float(k), seq=k,
                          odom=Odometry(x=x, y=y, yaw=yaw))

    try:
        for robot in ("zodom", "ztwin"):
            z.create_session(robot, "small", "dpso", None, 4)
        sources = [send("zodom", k, i).heading_source for k, i in enumerate(frames)]
        assert "odometry" in sources  # the odometry was fused: it gives the map heading
        last = sunny2.odometry[frames[-1]]
        bad = [({"x": 1e9, "y": 0.0, "yaw": 0.0}, 422, "less than or equal"),
               ({"x": float(last[0]) + 500.0, "y": float(last[1]), "yaw": float(last[2])},
                422, "more than 100 m"),
               ({"x": 0.0, "y": 0.0}, 422, "yaw")]
        image = sunny2.image_path(frames[-1] + 1).read_bytes()
        for odom, status, message in bad:
            with pytest.raises(SwarmlocError) as err:
                z._query("zodom/localize", image,
                         json.dumps({"t": 99.0, "seq": 99, "odom": odom}).encode())
            assert err.value.status == status and message in err.value.message
        assert z.session("zodom").frames == len(frames)
        for k, i in enumerate(frames):
            send("ztwin", k, i)
        nxt = len(frames), frames[-1] + 1
        a, b = send("zodom", *nxt), send("ztwin", *nxt)
        assert a.model_dump(exclude={"robot_id"}) == b.model_dump(exclude={"robot_id"})
    finally:
        for robot in ("zodom", "ztwin"):
            z.delete_session(robot)
        z.close()


def test_zenoh_get_shows_a_learning_session_s_progress(server, sunny2) -> None:
    """Zenoh's control ``get`` answers as ``GET /sessions/{id}``: a learning session's
    ``learning`` counts the frame it sent (a session's first frame is stopped by the path
    gate, so the shared map learns nothing here); a session that does not learn shows none."""
    z = ZenohClient([server["zenoh"]], mode="peer")
    try:
        z.create_session("zlearn", "small", learn=True, condition="sunny")
        z.create_session("zplain", "small")
        for robot in ("zlearn", "zplain"):
            z.localize(robot, sunny2.image_path(3).read_bytes(), t=0.0)
        lr = z.session("zlearn").learning
        assert lr is not None and lr.frames == 1 and lr.taught == 0, lr
        assert sum(lr.stopped.values()) == 1
        http = HttpClient(server["url"])
        assert http.session("zlearn").learning == lr
        http.close()
        assert z.session("zplain").learning is None
    finally:
        for robot in ("zlearn", "zplain"):
            z.delete_session(robot)
        z.close()


def test_a_frame_is_answered_while_a_control_query_waits(server, sunny2) -> None:
    """Regression: control queries (put, get, reset, delete) were answered on the one thread
    Zenoh runs the control queryable's callback on, fed by a bounded queue. A learning
    robot's delete waits for its learner (here: its gates held up), so every other robot's
    control query waited behind it, and once some 256 had queued, Zenoh's receiving thread
    blocked: no frame of any robot on the link was answered until the delete was done. Now
    control queries run on their own workers, and the callback returns at once."""
    service = server["service"]
    peer = _peer(server["zenoh"])
    get = json.dumps({"action": "get"}).encode()

    control = partial(_control, peer)
    try:
        time.sleep(0.5)  # let the peers connect before the first query
        control("zwalker", {"action": "put", "map": "small"})
        control("zteacher", {"action": "put", "map": "small", "learn": True})
        with service.learner._lock:  # the teacher's gates held up: its end waits for them
            ended = peer.get("swarmloc/zteacher/control",
                             payload=json.dumps({"action": "delete"}).encode(), timeout=60)
            time.sleep(0.3)
            crowd = [peer.get(f"swarmloc/zghost{i}/control", payload=get, timeout=60)
                     for i in range(300)]  # other robots' control queries meanwhile
            t0 = time.monotonic()
            (est,) = peer.get("swarmloc/zwalker/localize",
                              payload=sunny2.image_path(0).read_bytes(),
                              attachment=json.dumps({"t": 0.0}).encode(), timeout=20)
            waited = time.monotonic() - t0
            assert est.ok is not None, est.err.payload.to_bytes()
            assert json.loads(est.ok.payload.to_bytes())["robot_id"] == "zwalker"
            (other,) = peer.get("swarmloc/zwalker/control", payload=get, timeout=20)
            assert other.ok is not None and json.loads(other.ok.payload.to_bytes())[
                "robot_id"] == "zwalker"
            assert ended.try_recv() is None  # the delete is still waiting
        print(f"frame answered in {waited:.2f} s while a control query waited")
        (done,) = list(ended)
        assert done.ok is not None
        assert json.loads(done.ok.payload.to_bytes()) == {"deleted": "zteacher"}
        for handler in crowd:  # every one answered: no session (404) or too many (503)
            (r,) = list(handler)
            assert r.err is not None
            assert json.loads(r.err.payload.to_bytes())["status"] in (404, 503)
    finally:
        with contextlib.suppress(Exception):
            control("zwalker", {"action": "delete"})
        peer.close()


def test_a_frame_is_answered_while_map_queries_wait(server, sunny2) -> None:
    """Regression: ``@maps`` queries ran on the frame workers. Every map query but the list
    of the maps (a get too: it reads the newest version on disk) waits for the map admin,
    which a build or a learning session's images hold through a whole map write (here: held
    up by the test), so a few map queries took every frame worker and no robot's frame was
    answered until the write was done. Now map queries run on their own workers, and beyond
    a bounded backlog are answered 503 at once."""
    service = server["service"]
    peer = _peer(server["zenoh"])
    delete = json.dumps({"action": "delete"}).encode()

    control = partial(_control, peer)
    try:
        time.sleep(0.5)  # let the peers connect before the first query
        control("zmapper", {"action": "put", "map": "small"})
        with service.admin._lock:  # a map write in progress
            waiting = [peer.get(f"swarmloc/@maps/zgone{i}", attachment=delete, timeout=60)
                       for i in range(8)]  # more than the frame workers (4)
            waiting += [peer.get("swarmloc/@maps/zgone0", attachment=delete, timeout=60)
                        for _ in range(20)]  # beyond one map's backlog
            time.sleep(0.3)
            t0 = time.monotonic()
            (est,) = peer.get("swarmloc/zmapper/localize",
                              payload=sunny2.image_path(0).read_bytes(),
                              attachment=json.dumps({"t": 0.0}).encode(), timeout=20)
            waited = time.monotonic() - t0
            assert est.ok is not None, est.err.payload.to_bytes()
            assert json.loads(est.ok.payload.to_bytes())["robot_id"] == "zmapper"
            early = [r for r in (h.try_recv() for h in waiting) if r is not None]
            assert early and all(json.loads(r.err.payload.to_bytes())["status"] == 503
                                 for r in early)  # refused at once, not held
            assert len(early) < len(waiting)  # the others still wait for the map admin
        print(f"frame answered in {waited:.2f} s while map queries waited")
        for handler in waiting:  # every one answered: no such map (404) or too many (503)
            for r in handler:
                assert r.err is not None
                assert json.loads(r.err.payload.to_bytes())["status"] in (404, 503)
    finally:
        with contextlib.suppress(Exception):
            control("zmapper", {"action": "delete"})
        peer.close()
