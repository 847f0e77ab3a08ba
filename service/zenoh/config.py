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


class ZenohSecurityError(RuntimeError):
    """Zenoh would bypass the HTTP token: refused at start-up. The message is one line that
    says what to do (the CLI prints it as it is)."""


_SECURE_ZENOH = (
    "set up one of transport.auth.usrpwd.dictionary_file (user/password), "
    "transport.link.tls.enable_mtls with only tls/ or quic/ endpoints (mTLS), or "
    "access_control {enabled: true, default_permission: \"deny\"} in a Zenoh config file "
    "(--zenoh-config, SWARMLOC_ZENOH_CONFIG_FILE; README 'Hardening'), or turn Zenoh off "
    "(--no-zenoh, SWARMLOC_ZENOH_ENABLED=false), or accept an open Zenoh "
    "(SWARMLOC_ZENOH_UNAUTHENTICATED=true)")


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


def _get(cfg: zenoh.Config, key: str) -> Any:
    try:
        return json.loads(cfg.get_json(key))
    except Exception:  # a key this zenoh version does not know: not set
        return None


def _endpoints(cfg: zenoh.Config, key: str) -> list[str]:
    """A config's endpoints (a list, or per mode as in Zenoh's defaults)."""
    value = _get(cfg, key)
    if isinstance(value, dict):
        value = value.get(str(_get(cfg, "mode") or "peer"), [])
    return [str(e) for e in value] if isinstance(value, list) else []


def secured_by(cfg: zenoh.Config) -> str | None:
    """How a Zenoh config keeps anonymous peers out (user/password, mTLS on every link, or
    access control denying by default), or None when it does not."""
    usrpwd = _get(cfg, "transport/auth/usrpwd")
    if isinstance(usrpwd, dict) and usrpwd.get("dictionary_file"):
        return "user/password"
    tls = _get(cfg, "transport/link/tls")
    links = _endpoints(cfg, "listen/endpoints") + _endpoints(cfg, "connect/endpoints")
    if isinstance(tls, dict) and tls.get("enable_mtls") is True and links and \
            all(e.startswith(("tls/", "quic/")) for e in links):
        return "mTLS"
    acl = _get(cfg, "access_control")
    if isinstance(acl, dict) and acl.get("enabled") is True and \
            acl.get("default_permission") == "deny":
        return "access control"
    return None


def check_security(settings: Any) -> None:
    """With a bearer token on HTTP, Zenoh must keep anonymous peers out too (see
    ``secured_by``), or the operator must accept an open Zenoh explicitly; else
    ZenohSecurityError (or ZenohConfigError for a config file that cannot be read)."""
    if not settings.auth_token or settings.zenoh_unauthenticated:
        return
    if not settings.zenoh_config_file:
        raise ZenohSecurityError("HTTP needs a bearer token but Zenoh has no config file, so "
                                 "anyone could use Zenoh instead: " + _SECURE_ZENOH)
    if secured_by(service_zenoh_config(settings)) is None:
        raise ZenohSecurityError(
            f"HTTP needs a bearer token but the Zenoh config file {settings.zenoh_config_file} "
            "sets up no authentication or access control, so anyone could use Zenoh "
            "instead: " + _SECURE_ZENOH)
