"""Safe by default: without a token ``swarmloc serve`` listens on loopback only (HTTP and
Zenoh); a token or an explicit host opens it; the images and compose bind 0.0.0.0 by name."""

from __future__ import annotations

import contextlib
import json
import re
import socket
from pathlib import Path

import pytest
import yaml  # type: ignore[import-untyped]

from client.lab.processes import ServiceProcess
from service.maps.route_map import save_map
from service.settings import Settings

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture
def clean_env(monkeypatch: pytest.MonkeyPatch) -> None:
    for key in ("SWARMLOC_HOST", "SWARMLOC_AUTH_TOKEN", "SWARMLOC_ZENOH_LISTEN"):
        monkeypatch.delenv(key, raising=False)


def test_loopback_unless_a_token_or_a_host_is_given(clean_env, monkeypatch) -> None:
    s = Settings()
    assert s.host == "127.0.0.1"
    assert s.zenoh_listen == ["tcp/127.0.0.1:7447"]
    assert Settings(auth_token="t").host == "0.0.0.0"  # guarded by the token
    assert Settings(auth_token="t", host="127.0.0.1").host == "127.0.0.1"
    assert Settings(host="192.0.2.7").host == "192.0.2.7"
    monkeypatch.setenv("SWARMLOC_HOST", "0.0.0.0")  # asked for by name
    assert Settings().host == "0.0.0.0"


def _listening(port: int) -> list[str]:
    """Local addresses of the TCP sockets listening on ``port`` (IPv4 and IPv6)."""
    out = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            local, state = line.split()[1], line.split()[3]
            addr, _, hex_port = local.partition(":")
            if state == "0A" and int(hex_port, 16) == port:  # 0A: LISTEN
                out.append(addr)
    return out


def test_a_fresh_serve_answers_on_loopback_only(tmp_path: Path, small_map, clean_env) -> None:
    maps = tmp_path / "maps"
    maps.mkdir()
    save_map(small_map, maps / "small")
    proc = ServiceProcess("bind", {"SWARMLOC_MAPS_DIR": str(maps),
                                   "SWARMLOC_ZENOH_ENABLED": "false"}, tmp_path)
    del proc.env["SWARMLOC_HOST"]  # what `swarmloc serve` does without --host
    proc.start().wait_ready()  # it answers on 127.0.0.1
    try:
        assert _listening(proc.port) == ["0100007F"]  # 127.0.0.1, nothing else
        others = [a for a in _own_addresses() if not a.startswith("127.")]
        for addr in others:  # and nothing answers on this machine's other addresses
            with pytest.raises(OSError):
                socket.create_connection((addr, proc.port), timeout=2).close()
    finally:
        proc.stop()


def _own_addresses() -> list[str]:
    try:
        infos = socket.getaddrinfo(socket.gethostname(), None, socket.AF_INET)
    except OSError:
        return []
    return sorted({str(i[4][0]) for i in infos})


def _dockerfile_env(path: Path) -> dict[str, str]:
    text = (ROOT / path).read_text().replace("\\\n", " ")
    env: dict[str, str] = {}
    for line in re.findall(r"^ENV (.+)$", text, re.M):
        for key, value in re.findall(r"(SWARMLOC_\w+)=('[^']*'|\S+)", line):
            env[key] = value.strip("'")
    return env


def test_the_images_and_compose_bind_all_interfaces_by_name() -> None:
    root = _dockerfile_env(Path("Dockerfile"))
    assert root["SWARMLOC_HOST"] == "0.0.0.0"
    assert json.loads(root["SWARMLOC_ZENOH_LISTEN"]) == ["tcp/0.0.0.0:7447"]
    assert _dockerfile_env(Path("deploy/Dockerfile"))["SWARMLOC_HOST"] == "0.0.0.0"
    compose = yaml.safe_load((ROOT / "deploy" / "compose.yaml").read_text())
    for name in ("replica-1", "replica-2"):
        assert compose["services"][name]["environment"]["SWARMLOC_HOST"] == "0.0.0.0"


def test_free_ports_come_from_the_given_range_and_skip_taken_ones(monkeypatch) -> None:
    """``SWARMLOC_PORT_RANGE`` (the suite's workers get disjoint ones): every port is in the
    range, distinct, and a port something listens on is never handed out."""
    from service.server import PORT_RANGE_ENV, free_ports

    taken = _free_block(4)  # below every range the suite's workers and the system use
    with socket.socket() as held:
        held.bind(("127.0.0.1", taken))
        held.listen()
        monkeypatch.setenv(PORT_RANGE_ENV, f"{taken}-{taken + 4}")
        ports = free_ports(3)
        assert sorted(ports) == [taken + 1, taken + 2, taken + 3]
        with pytest.raises(RuntimeError, match="fewer than 4 free ports"):
            free_ports(4)
    for bad in ("20000", "x-y", "30000-20000", "80-90"):
        monkeypatch.setenv(PORT_RANGE_ENV, bad)
        with pytest.raises(ValueError, match="expected LO-HI"):
            free_ports(1)


def _free_block(n: int, start: int = 15_000) -> int:
    """The first port from ``start`` on with ``n`` consecutive ports free on loopback."""
    for lo in range(start, start + 4_000, n):
        with contextlib.ExitStack() as stack:
            try:
                for port in range(lo, lo + n):
                    stack.enter_context(socket.socket()).bind(("127.0.0.1", port))
            except OSError:
                continue
        return lo
    raise AssertionError("no free block of ports")
