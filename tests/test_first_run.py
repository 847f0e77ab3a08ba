"""The first minutes with the CLI, as real processes: the start-up banner of `swarmloc serve`,
and errors as one line that says what to do (the traceback only with --debug)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from client.lab.processes import ServiceProcess
from service import __version__
from service.maps.route_map import save_map
from service.server import free_port

SWARMLOC = Path(sys.executable).with_name("swarmloc")
# a bare-client install simulated: importing cv2 fails as if it were not installed
BLOCK_CV2 = '''
import sys

class _NoCv2:
    def find_spec(self, name, path=None, target=None):
        if name == "cv2" or name.startswith("cv2."):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None

sys.meta_path.insert(0, _NoCv2())
'''


def _swarmloc(args: list[str], env: dict[str, str] | None = None,
              cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(SWARMLOC), *args], capture_output=True, text=True, timeout=120,
                          env={**os.environ, **(env or {})}, cwd=cwd)


def _one_line_error(res: subprocess.CompletedProcess[str]) -> str:
    assert res.returncode in (1, 2), res
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
    assert "Traceback" not in res.stderr + res.stdout
    return lines[0]


def test_serve_prints_a_banner_with_its_urls(tmp_path: Path, small_map) -> None:
    maps = tmp_path / "maps"
    save_map(small_map, maps / "small")
    zenoh = f"tcp/127.0.0.1:{free_port()}"
    proc = ServiceProcess("banner", {
        "SWARMLOC_MAPS_DIR": str(maps), "SWARMLOC_ZENOH_LISTEN": f'["{zenoh}"]',
        "SWARMLOC_AUTH_TOKEN": "s3cret", "SWARMLOC_ZENOH_UNAUTHENTICATED": "true"}, tmp_path)
    try:
        proc.start().wait_ready()
        log = proc.log_tail(20_000)
    finally:
        proc.stop()
    url = f"http://127.0.0.1:{proc.port}"
    banner = log[log.index(f"swarmloc {__version__}\n"):].splitlines()[:8]
    rows = dict(re.split(r"\s{2,}", line.strip(), maxsplit=1) for line in banner[1:])
    assert rows["HTTP"].startswith(url + " ") and f"{url}/docs" in rows["HTTP"]
    assert rows["viewer"] == f"{url}/viewer?token=<SWARMLOC_AUTH_TOKEN>"
    assert rows["Zenoh"].startswith(f"listen {zenoh} ")
    assert rows["ROS 2"] == "off"
    assert rows["auth"].startswith("on") and "s3cret" not in log
    assert rows["maps"] == f"1 from {maps}/: small"
    assert rows["sessions"].startswith("in-process")


def test_zenoh_refusal_is_one_line_naming_the_ways_out(tmp_path: Path) -> None:
    args = ["serve", "--token", "s3cret", "--maps-dir", str(tmp_path), "--port",
            str(free_port())]
    line = _one_line_error(_swarmloc(args))
    assert "--no-zenoh" in line and "SWARMLOC_ZENOH_CONFIG_FILE" in line
    debug = _swarmloc(["--debug", *args])
    assert debug.returncode != 0 and "Traceback" in debug.stderr
    assert "ZenohSecurityError" in debug.stderr


def test_maps_through_redis_without_redis_is_one_line(tmp_path: Path) -> None:
    """`--maps-sync redis` needs the Redis session store: refused before anything starts."""
    line = _one_line_error(_swarmloc(["serve", "--maps-dir", str(tmp_path), "--port",
                                      str(free_port()), "--maps-sync", "redis"]))
    assert "needs the Redis session store" in line and "SWARMLOC_SESSION_STORE" in line


@pytest.mark.parametrize("command", [["world", "render"], ["serve"]])
def test_a_missing_extra_names_the_command_and_the_install(tmp_path: Path,
                                                           command: list[str]) -> None:
    (tmp_path / "sitecustomize.py").write_text(BLOCK_CV2)
    env = {"PYTHONPATH": os.pathsep.join(
        [str(tmp_path), *filter(None, [os.environ.get("PYTHONPATH")])])}
    args = [*command, str(tmp_path / "out")] if command[0] == "world" else command
    extra = "lab" if command[0] == "world" else "service"
    line = _one_line_error(_swarmloc(args, env, cwd=tmp_path))
    assert line == (f"error: swarmloc {' '.join(command)} needs the [{extra}] extra: pip "
                    f"install 'swarmloc[{extra}]' (module 'cv2' is not installed)")
    debug = _swarmloc(["--debug", *args], env, cwd=tmp_path)
    assert "Traceback" in debug.stderr and "ModuleNotFoundError" in debug.stderr


def test_an_unreachable_service_is_one_line(tmp_path: Path) -> None:
    url = f"http://127.0.0.1:{free_port()}"
    line = _one_line_error(_swarmloc(["map", "delete", "x", "--at", url]))
    assert "cannot reach the service" in line and "is the service running" in line
