"""Schemathesis against the OpenAPI schema of a real server: every operation, and stateful
runs along the schema's links (create a session, then send frames, reset, read, delete it).
No answer may be a 5xx, and every answer must conform to the schema (status code, content
type, body). Bounded to stay well under a minute."""

from __future__ import annotations

import os
import zlib
from collections.abc import Iterator

import hypothesis
import pytest
import schemathesis
from hypothesis import HealthCheck
from hypothesis import strategies as st
from schemathesis import checks

from service.engine.localization_service import LocalizationService
from service.maps.route_map import save_map
from service.server import free_port, running_server
from service.settings import Settings

SCALE = float(os.environ.get("SWARMLOC_FUZZ_SCALE", "1"))  # bench fuzz raises it
# the suite's own run (no SWARMLOC_FUZZ_SCALE) uses fixed examples (reproducible in CI)
FIXED = "SWARMLOC_FUZZ_SCALE" not in os.environ
CHECKS = [checks.not_a_server_error, checks.status_code_conformance,
          checks.content_type_conformance, checks.response_schema_conformance]


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory, small_map, sunny2) -> Iterator[str]:
    maps = tmp_path_factory.mktemp("fuzz_api_maps")
    save_map(small_map, maps / "small")
    frames = [sunny2.image_path(i).read_bytes() for i in range(0, 40, 8)]
    # frame bodies: real PNGs of the route (so sessions really step), or junk
    schemathesis.openapi.media_type("image/png", st.sampled_from(frames) | st.binary(
        max_size=64))
    settings = Settings(maps_dir=maps, host="127.0.0.1", port=free_port(), workers=2,
                        zenoh_enabled=False, max_particles=400, max_sessions=64)
    with running_server(LocalizationService(settings), zenoh=False) as url:
        yield url


def _schema(url: str) -> schemathesis.BaseSchema:
    return schemathesis.openapi.from_url(url + "/openapi.json")


def _fuzz_operation(api: str, op: schemathesis.APIOperation) -> None:
    """Hypothesis examples of one operation; none may be a 5xx or break the schema."""
    frames_op = op.path == "/sessions/{robot_id}/frames"

    # the frame route gets more examples: a case reaches the estimator only when its
    # body is a real PNG, its content type fits and its query is valid
    @hypothesis.given(case=op.as_strategy())
    @hypothesis.settings(max_examples=int((40 if frames_op else 8) * SCALE), deadline=None,
                         database=None, suppress_health_check=list(HealthCheck),
                         derandomize=FIXED)
    def run(case: schemathesis.Case) -> None:
        params = case.path_parameters or {}
        real_frame = frames_op and isinstance(case.body, bytes) \
            and case.body.startswith(b"\x89PNG")
        if "robot_id" in params and (real_frame or zlib.crc32(
                str(params["robot_id"]).encode()) % 2 == 0):
            params["robot_id"] = "fuzz"  # the live session: real frames, half the rest
        case.call_and_validate(base_url=api, checks=CHECKS, timeout=30)

    run()


def test_every_operation_answers_without_5xx(api: str) -> None:
    import httpx

    schema = _schema(api)
    assert httpx.put(api + "/sessions/fuzz", json={"seed": 1}).status_code == 201
    before = _frames(api)
    ops = [r.ok() for r in schema.get_all_operations()]
    assert any(op.path == "/sessions/{robot_id}/frames" for op in ops)
    for op in ops:
        if op.path in ("/events",):  # an endless stream, tested in test_events.py
            continue
        _fuzz_operation(api, op)
        if op.path.startswith("/sessions/{robot_id}") and op.method.upper() == "DELETE":
            httpx.put(api + "/sessions/fuzz", json={"seed": 1})
    assert _frames(api) > before  # real frames reached the estimator


def test_stateful_sessions_without_5xx(api: str) -> None:
    import httpx

    schema = _schema(api).include(path_regex="^/sessions")

    class Workflow(schema.as_state_machine()):  # type: ignore[misc]
        def __init__(self) -> None:
            # every example starts from no sessions: the same choices meet the same
            # service state (hypothesis replays examples and checks that they repeat)
            super().__init__()
            for info in httpx.get(api + "/sessions").json():
                httpx.delete(f"{api}/sessions/{info['robot_id']}")

        def get_call_kwargs(self, case: schemathesis.Case) -> dict:
            return {"base_url": api, "timeout": 30}

        def before_call(self, case: schemathesis.Case) -> None:
            # generated configs almost never pass the semantic checks (map extent, particle
            # ceiling, v0_min <= v0 <= v0_max): make every other one a plain valid session,
            # so the links lead to frames, resets and reads of a live session
            if case.operation.method.upper() == "PUT" and isinstance(case.body, dict) and \
                    hash(case.path_parameters.get("robot_id")) % 2 == 0:
                case.body = {"seed": 1}
            if case.operation.path.endswith("/frames") and case.query and \
                    hash(case.path_parameters.get("robot_id")) % 2 == 0:
                case.query = {}  # no random prior: most fall outside the map

        def validate_response(self, response: schemathesis.Response, case: schemathesis.Case,
                              **kwargs: object) -> None:
            case.validate_response(response, checks=CHECKS)

    before = _frames(api)
    Workflow.run(settings=hypothesis.settings(
        max_examples=int(10 * SCALE), stateful_step_count=6, deadline=None, database=None,
        suppress_health_check=list(HealthCheck), derandomize=FIXED))
    print("frames localized along the links:", _frames(api) - before)


def _frames(url: str) -> float:
    import httpx

    for line in httpx.get(url + "/metrics").text.splitlines():
        if line.startswith('swarmloc_frames_total{transport="http"}'):
            return float(line.rpartition(" ")[2])
    return 0.0
