"""``swarmloc serve`` (also ``swarmloc-service serve`` and ``python -m service serve``).

Importing this module is cheap (typer only): the ``swarmloc`` command registers ``serve``
from here, and the server's modules are imported when it runs.
"""

from __future__ import annotations

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
) -> None:
    """Run the localization service (HTTP + Zenoh). Flags override SWARMLOC_* variables."""
    try:
        from service.server import run
        from service.settings import Settings
    except ImportError as exc:
        typer.echo(f"error: the service needs the 'service' extra: pip install "
                   f"'swarmloc[service]' ({exc})", err=True)
        raise typer.Exit(2) from None

    overrides: dict[str, Any] = {k: v for k, v in {
        "host": host, "port": port, "maps_dir": maps_dir, "default_map": default_map,
        "default_estimator": default_estimator, "auth_token": token, "zenoh_enabled": zenoh,
        "zenoh_listen": zenoh_listen, "zenoh_connect": zenoh_connect,
        "ros2_enabled": ros2, "zenoh_config_file": zenoh_config,
        "session_store": session_store}.items() if v is not None}
    settings = Settings(**overrides)
    if demo:
        from service.demo import ensure_demo_map

        path = ensure_demo_map(settings.maps_dir)
        typer.echo(f"demo map: {path}")
    from service.engine.sqlite_store import SessionStoreError

    try:
        run(settings)
    except SessionStoreError as exc:  # a reason to give in one line, not a traceback
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None


@app.callback()
def _main() -> None:
    """swarmloc service: HTTP + Zenoh localization."""


def main() -> None:
    app()
