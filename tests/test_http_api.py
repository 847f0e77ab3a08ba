"""HTTP API through FastAPI's test client (real app, real maps on disk, real PNG/JPEG)."""

from __future__ import annotations

import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.engine.localization_service import LocalizationService
from service.http.app import create_app
from service.maps.route_map import save_map
from service.settings import Settings
from service.vision.imaging import encode_jpeg


@pytest.fixture(scope="module")
def maps_dir(tmp_path_factory: pytest.TempPathFactory, small_map) -> Path:
    d = tmp_path_factory.mktemp("svc_maps")
    save_map(small_map, d / "small")
    (d / "broken.swmap").write_bytes(b"not a map")  # reported, does not stop the others
    return d


def _client(maps_dir: Path, **kw) -> TestClient:
    settings = Settings(maps_dir=maps_dir, zenoh_enabled=False, **kw)
    return TestClient(create_app(LocalizationService(settings)))


@pytest.fixture()
def client(maps_dir: Path):
    with _client(maps_dir) as c:
        yield c


def _png(rnd, i: int) -> bytes:
    return rnd.image_path(i).read_bytes()


def test_health_ready_and_maps(client: TestClient, maps_dir: Path) -> None:
    assert client.get("/healthz").json()["status"] == "ok"
    assert client.get("/readyz").json() == {"status": "ready", "maps": ["small"]}
    maps = client.get("/maps").json()
    assert [m["name"] for m in maps] == ["small"] and maps[0]["n_images"] > 100
    detail = client.get("/maps/small").json()
    assert len(detail["positions"]) == maps[0]["n_images"] == len(detail["image_names"])
    r = client.get("/maps/nope")
    assert r.status_code == 404 and "unknown map 'nope'" in r.json()["error"]


def test_not_ready_without_maps(tmp_path: Path) -> None:
    with _client(tmp_path) as c:
        r = c.get("/readyz")
        assert r.status_code == 503 and "no maps loaded" in r.json()["error"]


def test_session_lifecycle_and_localization(client: TestClient, sunny2) -> None:
    r = client.put("/sessions/bot-1", json={"map": "small", "estimator": "dpso", "seed": 3})
    assert r.status_code == 201
    assert client.put("/sessions/bot-1", json={"seed": 3}).status_code == 200  # replaced
    errors = []
    for i in range(40):
        r = client.post(f"/sessions/bot-1/frames?t={i}.0&seq={i}",
                        content=_png(sunny2, i), headers={"content-type": "image/png"})
        assert r.status_code == 200, r.text
        est = r.json()
        errors.append(np.hypot(est["x"] - sunny2.truth_xy[i, 0], est["y"] - sunny2.truth_xy[i, 1]))
    assert est["seq"] == 40 and est["input_seq"] == 39 and est["robot_id"] == "bot-1"
    assert est["status"] == "tracking" and est["frame_id"] == "small"
    assert len(est["pose_covariance"]) == 36 and est["accuracy_m"] > 0
    assert np.mean(errors[20:]) < 3.0
    info = client.get("/sessions/bot-1").json()
    assert info["frames"] == 40 and info["last_estimate"]["seq"] == 40
    assert [s["robot_id"] for s in client.get("/sessions").json()] == ["bot-1"]
    reset = client.post("/sessions/bot-1/reset", json={"x": 1.0, "y": 2.0, "radius": 3.0})
    assert reset.status_code == 200
    assert client.delete("/sessions/bot-1").status_code == 204
    assert client.get("/sessions/bot-1").status_code == 404


def test_jpeg_frames_are_accepted(client: TestClient, sunny2) -> None:
    client.put("/sessions/jpg", json={})
    jpg = encode_jpeg(sunny2.load_image(3))
    r = client.post("/sessions/jpg/frames", content=jpg, headers={"content-type": "image/jpeg"})
    assert r.status_code == 200 and r.json()["comparisons"] > 0


@pytest.mark.parametrize(
    ("body", "ctype", "status", "message"),
    [
        (b"", "image/png", 400, "empty body"),
        (b"hello", "image/png", 400, "neither a PNG nor a JPEG"),
        (b"\x89PNG\r\n\x1a\n" + b"\x00" * 40, "image/png", 400, "IHDR"),
        (None, "image/gif", 415, "not supported"),
        (None, "image/jpeg", 400, "content type says image/jpeg but the body is a PNG"),
        ("truncated", "image/png", 400, "could not be decoded"),
    ],
)
def test_bad_frames_are_rejected_and_leave_the_session_intact(
    client: TestClient, sunny2, body, ctype, status, message
) -> None:
    client.put("/sessions/victim", json={"seed": 1})
    good = _png(sunny2, 0)
    assert client.post("/sessions/victim/frames?t=0", content=good,
                       headers={"content-type": "image/png"}).status_code == 200
    before = client.get("/sessions/victim").json()
    if body is None:
        body = good
    elif body == "truncated":
        body = good[: len(good) // 2]
    r = client.post("/sessions/victim/frames?t=1", content=body, headers={"content-type": ctype})
    assert r.status_code == status
    assert message in r.json()["error"]
    after = client.get("/sessions/victim").json()
    assert after["frames"] == before["frames"]
    assert after["last_estimate"] == before["last_estimate"]


def test_session_state_untouched_by_rejected_frame(maps_dir: Path, sunny2) -> None:
    """A rejected frame in between gives exactly the estimates of a run without it."""
    frames = [_png(sunny2, i) for i in range(8)]
    results = []
    for inject in (False, True):
        with _client(maps_dir) as c:
            c.put("/sessions/r", json={"seed": 9})
            out = []
            for i, f in enumerate(frames):
                if inject and i == 4:
                    bad = c.post("/sessions/r/frames", content=b"junk",
                                 headers={"content-type": "image/png"})
                    assert bad.status_code == 400
                out.append(c.post(f"/sessions/r/frames?t={i}", content=f,
                                  headers={"content-type": "image/png"}).json())
            results.append([(e["x"], e["y"], e["seq"]) for e in out])
    assert results[0] == results[1]


def test_limits_and_conflicts(maps_dir: Path, sunny2) -> None:
    with _client(maps_dir, max_body_bytes=150_000, max_pixels=320 * 240, max_sessions=2) as c:
        c.put("/sessions/a", json={})
        big = cv2.imencode(".png", np.random.default_rng(0).integers(
            0, 255, (480, 640), dtype=np.uint8))[1].tobytes()
        r = c.post("/sessions/a/frames", content=big, headers={"content-type": "image/png"})
        assert r.status_code == 413 and "limit is 150000 bytes" in r.json()["error"]
        wide = cv2.imencode(".png", np.zeros((240, 400), np.uint8))[1].tobytes()
        r = c.post("/sessions/a/frames", content=wide, headers={"content-type": "image/png"})
        assert r.status_code == 413 and "400x240" in r.json()["error"]
        ok = c.post("/sessions/a/frames?t=5", content=_png(sunny2, 0),
                    headers={"content-type": "image/png"})
        assert ok.status_code == 200
        old = c.post("/sessions/a/frames?t=4", content=_png(sunny2, 1),
                     headers={"content-type": "image/png"})
        assert old.status_code == 409 and "older than the last processed" in old.json()["error"]
        c.put("/sessions/b", json={})
        r = c.put("/sessions/c", json={})
        assert r.status_code == 503 and "session limit of 2" in r.json()["error"]
        r = c.put("/sessions/d", json={"estimator": "kalman"})
        assert r.status_code == 422
        r = c.put("/sessions/a", json={"params": {"swarm_size": 3}})
        assert r.status_code == 422 and "unknown parameter" in r.json()["error"]
        r = c.put("/sessions/bad id!", json={})
        assert r.status_code == 422
        r = c.post("/sessions/ghost/frames", content=_png(sunny2, 0),
                   headers={"content-type": "image/png"})
        assert r.status_code == 404 and "PUT /sessions/ghost" in r.json()["error"]
        metrics = c.get("/metrics").text
        assert 'swarmloc_rejected_inputs_total{reason="PayloadTooLarge"} 2.0' in metrics
        assert 'swarmloc_rejected_inputs_total{reason="Conflict"} 1.0' in metrics
        assert 'swarmloc_frames_total{transport="http"} 1.0' in metrics
        assert "swarmloc_sessions 2.0" in metrics


def test_bearer_token(maps_dir: Path) -> None:
    with _client(maps_dir, auth_token="s3cret") as c:
        assert c.get("/healthz").status_code == 200  # probes stay open
        r = c.get("/maps")
        assert r.status_code == 401 and "Bearer" in r.json()["error"]
        assert c.get("/maps", headers={"Authorization": "Bearer wrong"}).status_code == 401
        assert c.get("/maps", headers={"Authorization": "Bearer s3cret"}).status_code == 200


def test_idle_sessions_expire(maps_dir: Path) -> None:
    settings = Settings(maps_dir=maps_dir, zenoh_enabled=False, session_idle_s=0.2)
    service = LocalizationService(settings)
    with TestClient(create_app(service, expire_every_s=0.05)) as c:
        c.put("/sessions/sleepy", json={})
        done = threading.Event()
        done.wait(0.6)
        assert c.get("/sessions/sleepy").status_code == 404
        assert "swarmloc_sessions_expired_total 1.0" in c.get("/metrics").text


def test_openapi_spec_is_valid(client: TestClient) -> None:
    from openapi_spec_validator import validate

    spec = client.get("/openapi.json").json()
    validate(spec)
    assert "/sessions/{robot_id}/frames" in spec["paths"]
    body = spec["paths"]["/sessions/{robot_id}/frames"]["post"]["requestBody"]["content"]
    assert set(body) == {"image/png", "image/jpeg", "application/octet-stream"}


def test_implicit_session_creation_never_replaces_one(maps_dir: Path) -> None:
    from service.api.models import SessionConfig

    svc = LocalizationService(Settings(maps_dir=maps_dir, zenoh_enabled=False))
    _, created = svc.put_session("r", SessionConfig(seed=5))
    loc = svc.session("r").localizer
    assert svc.ensure_session("r").localizer is loc
    _, created_again = svc.put_session("r", SessionConfig(seed=6), replace=False)
    assert created and not created_again
    assert svc.session("r").localizer is loc and loc.seed == 5
    _, replaced_created = svc.put_session("r", SessionConfig(seed=6))
    assert not replaced_created and svc.session("r").localizer.seed == 6
