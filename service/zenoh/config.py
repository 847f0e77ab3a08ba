"""The one Zenoh config builder of the service, the client and the tests.

A Zenoh config file (JSON5, ``zenoh.Config.from_file``) is how Zenoh users configure TLS or
mTLS (``transport/link/tls``), user/password authentication (``transport/auth/usrpwd``) and
access control (``access_control``); README "Hardening" shows a locked-down one. The explicit
arguments are applied on top of the file: with a file, ``None`` leaves the file's value.
Without a file the defaults are safe: no multicast scouting, no shared memory, and the
caller passes loopback listen endpoints (the service's default).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # zenoh is the [zenoh] extra: imported where a session is opened
    import zenoh


class ZenohConfigError(ValueError):
    """The Zenoh config file or a value could not be used."""


def zenoh_config(*, config_file: str | Path | None = None, mode: str | None = None,
                 connect: Sequence[str] | None = None, listen: Sequence[str] | None = None,
                 multicast_scouting: bool | None = None,
                 extra: dict[str, Any] | None = None) -> zenoh.Config:
    """A ``zenoh.Config``: the file (if any), then each argument that is not None, then
    ``extra`` (key path -> JSON value, e.g. ``{"transport/link/tls/enable_mtls": True}``)."""
    import zenoh

    if config_file is not None:
        path = Path(config_file)
        if not path.is_file():
            raise ZenohConfigError(f"Zenoh config file {path} does not exist")
        try:
            cfg = zenoh.Config.from_file(str(path))
        except Exception as exc:  # zenoh raises its own ZError with the parser's message
            raise ZenohConfigError(f"Zenoh config file {path}: {exc}") from None
    values: dict[str, Any] = {}
    if config_file is None:
        cfg = zenoh.Config()
        if multicast_scouting is None:
            multicast_scouting = False
        # shared memory: measured ~16 MiB of resident memory per peer connection that is
        # never returned (bench load --soak-reconnect); frames arrive over the network anyway
        values["transport/shared_memory/enabled"] = False
    if mode is not None:
        values["mode"] = mode
    if connect:
        values["connect/endpoints"] = list(connect)
    if listen:
        values["listen/endpoints"] = list(listen)
    if multicast_scouting is not None:
        values["scouting/multicast/enabled"] = multicast_scouting
    values.update(extra or {})
    for key, value in values.items():
        try:
            cfg.insert_json5(key, json.dumps(value))
        except Exception as exc:
            raise ZenohConfigError(f"Zenoh config {key}={value!r}: {exc}") from None
    return cfg


def service_zenoh_config(settings: Any) -> zenoh.Config:
    """The service's config from ``Settings``: with a file, only the zenoh_* settings that
    were given explicitly (environment or flags) override it."""
    given = settings.model_fields_set if settings.zenoh_config_file else None

    def pick(name: str) -> Any:
        return getattr(settings, name) if given is None or name in given else None

    return zenoh_config(config_file=settings.zenoh_config_file, mode=pick("zenoh_mode"),
                        connect=pick("zenoh_connect"), listen=pick("zenoh_listen"),
                        multicast_scouting=pick("zenoh_multicast_scouting"))
