"""Issue 16's defects, one regression test each, against a real uvicorn server (and a real
Zenoh bridge on loopback). Each of these failed on the code before the fix."""

from __future__ import annotations

import io
import json
import math
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
import zenoh

from client.transports import SwarmlocError, ZenohClient
from service.engine.localization_service import LocalizationService
from service.engine.localizer import Localizer
from service.estimators.base import EstimatorStateError
from service.http.app import create_app
from service.maps.route_map import RouteMap, save_map
from service.server import build_app, free_port, running_server
from service.settings import Settings
from service.vision.imaging import encode_png
from service.zenoh.config import ZenohSecurityError, zenoh_config

PNG = {"content-type": "image/png"}


def _settings(maps: Path, **kw: object) -> Settings:
    return Settings(maps_dir=maps, host="127.0.0.1", port=free_port(),
                    zenoh_listen=[f"tcp/127.0.0.1:{free_port()}"], workers=2, **kw)


@pytest.fixture(scope="module")
def srv(tmp_path_factory: pytest.TempPathFactory, small_map) -> Iterator[dict]:
    maps = tmp_path_factory.mktemp("hard_maps")
    save_map(small_map, maps / "small")
    settings = _settings(maps, max_particles=5000)
    service = LocalizationService(settings)
    with running_server(service) as url, httpx.Client(base_url=url, timeout=60) as http:
        yield {"url": url, "http": http, "service": service,
               "zenoh": settings.zenoh_listen[0]}


def _frame(http: httpx.Client, robot: str, data: bytes, **query: object) -> httpx.Response:
    return http.post(f"/sessions/{robot}/frames", params=query, content=data, headers=PNG)


def _send(http: httpx.Client, method: str, url: str, body: object) -> httpx.Response:
    """JSON with NaN / Infinity as Python writes them (httpx's json= refuses them)."""
    return http.request(method, url, content=json.dumps(body).encode(),
                        headers={"content-type": "application/json"})


def _fresh(http: httpx.Client, robot: str, **cfg: object) -> None:
    r = http.put(f"/sessions/{robot}", json={"map": "small", "seed": 1, **cfg})
    assert r.status_code in (200, 201), r.text


# ---- 1. no input breaks a session ---------------------------------------------------------
@pytest.mark.parametrize("query", [
    {"prior_x": 1e200, "prior_y": 1e200, "prior_radius": 5},
    {"prior_x": "nan", "prior_y": 0},
    {"prior_x": 5e6, "prior_y": 0},  # finite, but far outside the map's extent + margin
])
def test_bad_prior_is_refused_and_the_session_keeps_working(srv, sunny2, query) -> None:
    http = srv["http"]
    _fresh(http, "prior")
    frame = sunny2.image_path(3).read_bytes()
    r = _frame(http, "prior", frame, t=0, **query)
    assert r.status_code == 422 and "prior" in r.json()["error"]
    assert http.get("/sessions/prior").json()["frames"] == 0
    ok = _frame(http, "prior", frame, t=1)
    assert ok.status_code == 200, ok.text
    assert math.isfinite(ok.json()["x"]) and ok.json()["seq"] == 1


@pytest.mark.parametrize("pose", [{"x": float("nan"), "y": 0.0}, {"x": 1e200, "y": 1e200},
                                  {"x": 0.0, "y": 0.0, "radius": float("inf")}])
def test_bad_initial_pose_and_reset_are_refused(srv, sunny2, pose) -> None:
    http = srv["http"]
    r = _send(http, "PUT", "/sessions/init", {"map": "small", "initial_pose": pose})
    assert r.status_code == 422 and r.json()["error"].startswith("invalid request")
    _fresh(http, "init")
    r = _send(http, "POST", "/sessions/init/reset", pose)
    assert r.status_code == 422
    ok = _frame(http, "init", sunny2.image_path(3).read_bytes(), t=0)
    assert ok.status_code == 200 and math.isfinite(ok.json()["x"])


def test_zenoh_reset_with_nan_is_refused_like_http(srv, sunny2) -> None:
    http = srv["http"]
    _fresh(http, "znan")
    z = ZenohClient([srv["zenoh"]], mode="peer", timeout=20)
    try:
        with pytest.raises(SwarmlocError) as ez:
            z._control("znan", {"action": "reset", "x": float("nan"), "y": 0.0})
        rh = _send(http, "POST", "/sessions/znan/reset", {"x": float("nan"), "y": 0.0})
        assert ez.value.status == rh.status_code == 422
        assert ez.value.message == rh.json()["error"]
        # a lone x: the same 422 on both (Zenoh used to reset globally)
        with pytest.raises(SwarmlocError) as ez:
            z._control("znan", {"action": "reset", "x": 1.0})
        rh = http.post("/sessions/znan/reset", json={"x": 1.0})
        assert ez.value.status == rh.status_code == 422
        assert ez.value.message == rh.json()["error"]
        est = z.localize("znan", sunny2.image_path(3).read_bytes(), t=0.0)
        assert math.isfinite(est.x)
    finally:
        z.close()


@pytest.mark.parametrize("params", [{"n_particles": 2.9}, {"omega": "fast"},
                                    {"swarm": 3}, {"v0": 0.5}])
def test_bad_params_get_the_same_422_over_http_and_zenoh(srv, params) -> None:
    z = ZenohClient([srv["zenoh"]], mode="peer", timeout=20)
    try:
        with pytest.raises(SwarmlocError) as ez:
            z.create_session("same422", "small", params=params)
    finally:
        z.close()
    rh = srv["http"].put("/sessions/same422", json={"map": "small", "params": params})
    assert ez.value.status == rh.status_code == 422
    assert ez.value.message == rh.json()["error"]


def test_estimator_state_never_stays_non_finite(small_map) -> None:
    loc = Localizer(small_map, "dpso", None, 0)
    est = loc.estimator
    est.step(lambda ids: np.zeros(len(list(ids))), 0.0)
    x = est.particles()
    assert x is not None
    est.place(np.ones(len(x), bool), np.full_like(x, np.nan))  # a bug elsewhere, simulated
    with pytest.raises(EstimatorStateError):
        est.step(lambda ids: np.zeros(len(list(ids))), 1.0)
    res = est.step(lambda ids: np.zeros(len(list(ids))), 2.0)  # re-initialised: works
    assert np.isfinite(res.position).all() and np.isfinite(est.particles()).all()
    with pytest.raises(ValueError, match="finite"):
        est.reset((float("nan"), 0.0), 5.0)


# ---- 2. unhandled inputs gave 500 -------------------------------------------------------
def test_huge_radius_infinite_params_and_non_ascii_auth_are_4xx(srv, sunny2,
                                                                 tmp_path: Path) -> None:
    http = srv["http"]
    _fresh(http, "rad")
    frame = sunny2.image_path(3).read_bytes()
    for radius in (1e6, "inf"):
        r = _frame(http, "rad", frame, prior_x=0, prior_y=0, prior_radius=radius)
        assert r.status_code == 422, r.text
        r = _send(http, "POST", "/sessions/rad/reset",
                  {"x": 0.0, "y": 0.0, "radius": float(radius)})
        assert r.status_code == 422
    r = http.put("/sessions/inf", content=b'{"params": {"n_particles": Infinity}}',
                 headers={"content-type": "application/json"})
    assert r.status_code == 422 and "n_particles" in r.json()["error"]
    with running_server(LocalizationService(_settings(
            srv["service"].settings.maps_dir, auth_token="tok"), ), zenoh=False) as url:
        bad = "Bearer t\u00f6k\u00e9n".encode("latin-1")
        r = httpx.get(url + "/maps", headers={"Authorization": bad})
        assert r.status_code == 401 and "Bearer" in r.json()["error"]


# ---- 3. cost limits -----------------------------------------------------------------------
@pytest.mark.parametrize(("n", "message"), [
    (10**9, "ceiling of 5000"),
    (10**7, "ceiling of 5000"),
    (6000, "ceiling of 5000"),  # the service's setting (SWARMLOC_MAX_PARTICLES)
    (2.9, "valid integer"),  # used to be truncated to 2
])
def test_particle_counts_are_bounded_and_never_truncated(srv, n, message) -> None:
    r = srv["http"].put("/sessions/cost", json={"params": {"n_particles": n}})
    assert r.status_code == 422 and message in r.json()["error"], r.text
    assert srv["http"].get("/sessions/cost").status_code == 404


def test_params_models_have_a_hard_particle_limit() -> None:
    from service.api.params import ParamError
    from service.estimators.registry import params_for

    for estimator in ("dpso", "pf-g"):
        with pytest.raises(ParamError, match="less than or equal to 100000"):
            params_for(estimator, {"n_particles": 10**9})


# ---- 4. Zenoh security --------------------------------------------------------------------
def test_zenoh_defaults_are_loopback_without_multicast() -> None:
    s = Settings()
    assert s.zenoh_listen == ["tcp/127.0.0.1:7447"] and not s.zenoh_multicast_scouting
    cfg = zenoh_config(mode="peer", listen=s.zenoh_listen)
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    assert json.loads(cfg.get_json("transport/shared_memory/enabled")) is False


def test_token_without_zenoh_security_refuses_to_start(tmp_path: Path) -> None:
    with pytest.raises(ZenohSecurityError, match="SWARMLOC_ZENOH_CONFIG_FILE"):
        build_app(Settings(maps_dir=tmp_path, auth_token="tok"))
    build_app(Settings(maps_dir=tmp_path, auth_token="tok", zenoh_enabled=False))


def test_zenoh_frames_create_no_session_with_auth_or_before_decoding(srv, small_map,
                                                                       sunny2) -> None:
    z = ZenohClient([srv["zenoh"]], mode="peer", timeout=20)
    try:  # no auth here: still, a frame that does not decode creates no session
        with pytest.raises(SwarmlocError) as exc:
            z.localize("junk-robot", b"junk")
        assert exc.value.status == 400
        assert srv["http"].get("/sessions/junk-robot").status_code == 404
    finally:
        z.close()
    settings = _settings(srv["service"].settings.maps_dir, auth_token="tok",
                         zenoh_unauthenticated=True)
    with running_server(LocalizationService(settings)) as url:
        z = ZenohClient(settings.zenoh_listen, mode="peer", timeout=20)
        try:
            with pytest.raises(SwarmlocError) as exc:
                z.localize("intruder", sunny2.image_path(0).read_bytes())
            assert exc.value.status == 404
        finally:
            z.close()
        r = httpx.get(url + "/sessions", headers={"Authorization": "Bearer tok"})
        assert r.json() == []


# ---- 5. Zenoh control answers every query -------------------------------------------------
def test_zenoh_control_answers_every_query(srv) -> None:
    peer = zenoh.open(zenoh_config(mode="peer", connect=[srv["zenoh"]]))
    try:
        cases = [
            ({"action": "put", "params": {"n_particles": float("inf")}}, 422),
            ({"action": "get"}, 404),  # unknown robot
            ({"action": "fly"}, 400),
            ({"action": "put", "params": {"n_particles": 2.9}}, 422),
            ({"action": "put", "initial_pose": {"x": 1e300, "y": 0}}, 422),
            ([1, 2], 400),
        ]
        for body, status in cases:
            replies = list(peer.get("swarmloc/ctl-ghost/control",
                                    payload=json.dumps(body).encode(), timeout=20))
            assert len(replies) == 1, body
            assert replies[0].err is not None, body
            err = json.loads(replies[0].err.payload.to_bytes())
            assert err["status"] == status, (body, err)
        replies = list(peer.get("swarmloc/ctl-ghost/control", payload=b"\xff{", timeout=20))
        assert len(replies) == 1 and json.loads(replies[0].err.payload.to_bytes())[
            "status"] == 400
    finally:
        peer.close()


# ---- 6. one bad map does not take the service down ----------------------------------------
def _write_map(m: RouteMap, path: Path, **changes: object) -> None:
    """Save ``m`` with ``changes`` and a valid checksum, bypassing RouteMap's checks."""
    fake = object.__new__(RouteMap)
    fake.__dict__.update({**m.__dict__, **changes})
    save_map(fake, path)


def test_bad_maps_are_skipped_and_named(tmp_path: Path, small_map,
                                        caplog: pytest.LogCaptureFixture) -> None:
    save_map(small_map, tmp_path / "a_good")
    pos = np.array(small_map.positions, float)
    pos[3, 0] = np.nan
    _write_map(small_map, tmp_path / "b_nan", name="nanmap", positions=pos)
    _write_map(small_map, tmp_path / "c_names", name="fewnames",
               image_names=small_map.image_names[:-5])
    _write_map(small_map, tmp_path / "d_dup", name="small")
    with caplog.at_level("ERROR", logger="swarmloc"):
        service = LocalizationService(Settings(maps_dir=tmp_path, zenoh_enabled=False))
    assert sorted(service.maps) == ["small"]
    assert service.maps["small"].path == tmp_path / "a_good.swmap"
    errs = service.load_errors
    assert "not all finite" in errs["b_nan.swmap"] and "b_nan.swmap" in errs["b_nan.swmap"]
    assert "image names for" in errs["c_names.swmap"]
    assert "already loaded from a_good.swmap" in errs["d_dup.swmap"]
    for name in ("b_nan.swmap", "c_names.swmap", "d_dup.swmap"):
        assert name in caplog.text


# ---- 7. smaller defects ---------------------------------------------------------------------
def test_error_bodies_are_json_errors_everywhere(srv) -> None:
    http = srv["http"]
    r = http.get("/no/such/route")
    assert r.status_code == 404 and "no such route" in r.json()["error"]
    r = http.patch("/sessions/x")
    assert r.status_code == 405 and "PATCH" in r.json()["error"]
    r = http.put("/sessions/x", content=b"\xff\xfe{", headers={"content-type":
                                                             "application/json"})
    assert r.status_code in (400, 422)
    assert set(r.json()) <= {"error", "detail"} and isinstance(r.json()["error"], str)


def test_openapi_and_docs_need_the_token(tmp_path: Path) -> None:
    settings = Settings(maps_dir=tmp_path, host="127.0.0.1", port=free_port(),
                        auth_token="tok", zenoh_enabled=False)
    with running_server(LocalizationService(settings), zenoh=False) as url:
        for path in ("/openapi.json", "/docs"):
            r = httpx.get(url + path)
            assert r.status_code == 401 and "error" in r.json()
        r = httpx.get(url + "/openapi.json", headers={"Authorization": "Bearer tok"})
        assert r.status_code == 200 and "/sessions/{robot_id}/frames" in r.json()["paths"]
        r = httpx.get(url + "/docs?token=tok")
        assert r.status_code == 200 and "/openapi.json?token=tok" in r.text
        assert httpx.get(url + "/healthz").status_code == 200


def test_exif_rotated_jpeg_is_accepted(srv, sunny2) -> None:
    from PIL import Image

    img = Image.fromarray(sunny2.load_image(3))
    exif = Image.Exif()
    exif[0x0112] = 6  # orientation: rotate 90 degrees clockwise to display
    buf = io.BytesIO()
    img.save(buf, "JPEG", exif=exif.tobytes(), quality=90)
    _fresh(srv["http"], "phone")
    r = srv["http"].post("/sessions/phone/frames", content=buf.getvalue(),
                         headers={"content-type": "image/jpeg"})
    assert r.status_code == 200, r.text


def test_tiny_frame_is_rejected_without_advancing(srv, sunny2) -> None:
    http = srv["http"]
    _fresh(http, "tiny")
    for shape in ((1, 1), (8, 200)):
        r = _frame(http, "tiny", encode_png(np.zeros(shape, np.uint8)), t=0)
        assert r.status_code == 400 and "at least 16x16" in r.json()["error"]
    assert http.get("/sessions/tiny").json()["frames"] == 0


def test_shutdown_refuses_new_frames_with_503(tmp_path: Path, small_map, sunny2) -> None:
    save_map(small_map, tmp_path / "small")
    service = LocalizationService(_settings(tmp_path, shutdown_deadline_s=5.0))
    with running_server(service, zenoh=False) as url:
        http = httpx.Client(base_url=url, timeout=30)
        _fresh(http, "late")
        assert _frame(http, "late", sunny2.image_path(0).read_bytes()).status_code == 200
        service.begin_shutdown()
        r = _frame(http, "late", sunny2.image_path(1).read_bytes())
        assert r.status_code == 503 and "shutting down" in r.json()["error"]
        assert http.get("/readyz").status_code == 503
        assert http.get("/sessions/late").json()["frames"] == 1
        http.close()
    assert service.wait_idle(1.0)


def test_params_are_documented_in_the_openapi_schema(tmp_path: Path) -> None:
    from fastapi.testclient import TestClient

    app = create_app(LocalizationService(Settings(maps_dir=tmp_path, zenoh_enabled=False)))
    with TestClient(app) as c:
        spec = c.get("/openapi.json").json()
    params = spec["components"]["schemas"]["SessionConfig"]["properties"]["params"]
    dpso = params["anyOf"][0]
    assert dpso["additionalProperties"] is False
    n = dpso["properties"]["n_particles"]
    assert n["type"] == "integer" and n["maximum"] == 100_000 and "swarm size" in \
        n["description"]
