"""``swarmloc serve`` (also ``swarmloc-service serve`` and ``python -m service serve``), and
``run_cli``: every command's errors as one line that says what to do.

Importing this module is cheap (typer only): the ``swarmloc`` command registers ``serve``
from here, and the server's modules are imported when it runs.
"""

from __future__ import annotations

import os
import sys
import traceback
from pathlib import Path
from typing import Annotated, Any

import typer

app = typer.Typer(help="swarmloc service: HTTP + Zenoh localization.", no_args_is_help=True,
                  rich_markup_mode=None, pretty_exceptions_enable=False)


@app.command("serve")
def serve(
    host: Annotated[str | None, typer.Option(
        help="bind address [SWARMLOC_HOST] (default: 127.0.0.1, loopback only; 0.0.0.0 "
             "when a token is set)")] = None,
    port: Annotated[int | None, typer.Option(help="HTTP port [SWARMLOC_PORT]")] = None,
    maps_dir: Annotated[Path | None, typer.Option(help="maps directory [SWARMLOC_MAPS_DIR]")]
    = None,
    demo: Annotated[bool, typer.Option(
        help="build MAPS_DIR/demo.swmap first if it is missing (from the round shipped in "
             "service/demo)")] = False,
    default_map: Annotated[str | None, typer.Option(help="[SWARMLOC_DEFAULT_MAP]")] = None,
    default_estimator: Annotated[str | None, typer.Option(help="dpso | pf-g | pf-l")] = None,
    token: Annotated[str | None, typer.Option(help="bearer token [SWARMLOC_AUTH_TOKEN]")] = None,
    zenoh: Annotated[bool | None, typer.Option(help="serve Zenoh too [SWARMLOC_ZENOH_ENABLED]")]
    = None,
    zenoh_listen: Annotated[list[str] | None, typer.Option(help="Zenoh listen endpoint")] = None,
    zenoh_connect: Annotated[list[str] | None, typer.Option(help="Zenoh connect endpoint")]
    = None,
    ros2: Annotated[bool | None, typer.Option(
        help="speak ROS 2 CDR messages on Zenoh too [SWARMLOC_ROS2_ENABLED]")] = None,
    zenoh_config: Annotated[Path | None, typer.Option(
        help="Zenoh JSON5 config file: TLS, user/password, ACL "
             "[SWARMLOC_ZENOH_CONFIG_FILE]")] = None,
    session_store: Annotated[str | None, typer.Option(
        help="sqlite (default: MAPS_DIR/sessions.sqlite, kept across a kill), "
             "sqlite:////path/file.sqlite, memory, or redis://host:port/db "
             "[SWARMLOC_SESSION_STORE]")] = None,
    maps_sync: Annotated[str | None, typer.Option(
        help="directory (replicas share one maps directory) or redis (a maps directory "
             "each, map files through the Redis session store) [SWARMLOC_MAPS_SYNC]")] = None,
) -> None:
    """Run the localization service (HTTP + Zenoh). Flags override SWARMLOC_* variables."""
    from service.server import run  # without the [service] extra: run_cli says so
    from service.settings import Settings

    overrides: dict[str, Any] = {k: v for k, v in {
        "host": host, "port": port, "maps_dir": maps_dir, "default_map": default_map,
        "default_estimator": default_estimator, "auth_token": token, "zenoh_enabled": zenoh,
        "zenoh_listen": zenoh_listen, "zenoh_connect": zenoh_connect,
        "ros2_enabled": ros2, "zenoh_config_file": zenoh_config,
        "session_store": session_store, "maps_sync": maps_sync}.items() if v is not None}
    settings = Settings(**overrides)
    if settings.zenoh_enabled:
        from service.zenoh.config import check_security

        check_security(settings)  # refuse before the demo map is built
    if demo:
        from service.demo import ensure_demo_map

        path = ensure_demo_map(settings.maps_dir, progress=True)
        typer.echo(f"demo map: {path}")
    from service.engine.sqlite_store import SessionStoreError

    try:
        run(settings)
    except SessionStoreError as exc:  # a reason to give in one line, not a traceback
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None


DebugOpt = Annotated[bool, typer.Option(
    "--debug", help="show the traceback of an error (otherwise: one line saying what to do)")]


@app.callback()
def _main(debug: DebugOpt = False) -> None:
    """swarmloc service: HTTP + Zenoh localization."""


def main() -> None:
    run_cli(app)


# ---- one-line errors ----------------------------------------------------------------------
#: the extra that installs each optional module (pyproject.toml's optional dependencies)
EXTRA_OF_MODULE = {
    "cv2": "service", "scipy": "service", "fastapi": "service", "starlette": "service",
    "uvicorn": "service", "httptools": "service", "uvloop": "service", "numba": "service",
    "numkong": "service", "prometheus_client": "service", "pydantic_settings": "service",
    "threadpoolctl": "service", "msgpack": "service", "zenoh": "zenoh", "pyproj": "geo",
    "redis": "redis", "rosbags": "ros", "matplotlib": "lab", "playwright": "lab"}
_SETUP, _RUNTIME = 2, 1  # exit codes: fix the install/input/config; the run failed


def run_cli(app: typer.Typer, argv: list[str] | None = None) -> None:
    """Run a typer app; an error ends it with one line on stderr that says what to do (exit
    2: fix the install, the input or the configuration; 1: the run failed). ``--debug``
    (before the command) shows the traceback instead."""
    args = sys.argv[1:] if argv is None else argv
    try:
        app(args=args)
    except KeyboardInterrupt:
        raise SystemExit(130) from None
    except Exception as exc:
        if "--debug" in _global_args(args) or os.environ.get("SWARMLOC_DEBUG") == "1":
            raise
        message, code = explain(exc, "swarmloc " + " ".join(_command_words(app, args)))
        typer.echo(f"error: {message}", err=True)
        raise SystemExit(code) from None


def _global_args(args: list[str]) -> list[str]:
    """The options before the first command word (where --debug belongs)."""
    out = []
    for a in args:
        if not a.startswith("-"):
            break
        out.append(a)
    return out


def _command_words(app: typer.Typer, args: list[str]) -> list[str]:
    """The command path in ``args`` (``['world', 'render']``)."""
    cmd: Any = typer.main.get_command(app)
    words = []
    for a in args:
        if a.startswith("-"):
            continue
        commands = getattr(cmd, "commands", None)  # a group (typer may vendor click)
        if not isinstance(commands, dict) or a not in commands:
            break
        words.append(a)
        cmd = commands[a]
    return words


def explain(exc: BaseException, command: str) -> tuple[str, int]:
    """One line for an error, and the exit code. Errors are recognised by class name, so that
    this module imports nothing heavy (the error may be that an import failed)."""
    names = {c.__name__ for c in type(exc).__mro__}
    if isinstance(exc, ModuleNotFoundError) and exc.name:
        module = exc.name.split(".")[0]
        extra = "lab" if _raised_in(exc, f"client{os.sep}lab{os.sep}") else \
            EXTRA_OF_MODULE.get(module)
        if extra is not None:
            return (f"{command.strip()} needs the [{extra}] extra: pip install "
                    f"'swarmloc[{extra}]' (module '{module}' is not installed)", _SETUP)
    if "ZenohSecurityError" in names:
        return (f"{exc}; on the command line: --zenoh-config FILE, or --no-zenoh to serve "
                "HTTP only", _SETUP)
    if names & {"MapError", "DatasetError"}:
        return str(exc), _SETUP
    if "SwarmlocError" in names:
        status, message = getattr(exc, "status", 0), getattr(exc, "message", str(exc))
        if status == 0:
            hint = " (is the service running, and the URL right?)" \
                if message.startswith("cannot reach") else ""
            return message + hint, _RUNTIME
        return f"the service answered {status}: {message}", _RUNTIME
    if "ServiceError" in names:
        return getattr(exc, "message", str(exc)), _SETUP
    if "ValidationError" in names and hasattr(exc, "errors"):
        from service.api.errors import describe_errors

        return (f"invalid settings (flags or SWARMLOC_* variables): "
                f"{describe_errors(exc.errors())}", _SETUP)
    if "TransportError" in names:  # httpx: connection refused, timeout, ...
        request = getattr(exc, "_request", None)
        where = f" {request.url}" if request is not None else ""
        return (f"cannot reach{where}: {exc or type(exc).__name__} (is the service running, "
                "and the URL right?)", _RUNTIME)
    if isinstance(exc, OSError) and exc.filename is not None:
        return f"{exc.strerror or exc}: {exc.filename}", _SETUP
    return (f"{type(exc).__name__}: {exc} (run 'swarmloc --debug {command[9:].strip()} ...' "
            "for the traceback)", _RUNTIME)


def _raised_in(exc: BaseException, part: str) -> bool:
    """Whether a frame of the traceback is in a file whose path contains ``part``."""
    return any(part in frame.filename for frame in traceback.extract_tb(exc.__traceback__))
