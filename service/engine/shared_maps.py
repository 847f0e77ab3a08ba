"""A maps directory shared by several services (replicas): the maps served follow its files.

A service serves the maps it loaded at start-up and those uploaded, built or learned through
it. Replicas on one maps directory (deploy/compose.yaml's one volume) also see files that
another replica wrote: a new map (an upload or a build through it), a new version (a replace,
a learned experience: ``MapAdmin.refresh`` reloads it) or none left (a delete).
``DirectoryFollower`` keeps this service in step with those files:

- ``discover(name)``: a map this service does not serve but whose file ``NAME.swmap`` is in
  the directory is loaded (its header read, its images checked on first use, as at start-up)
  and served from then on, so that a session, a map request, an upload's precondition or a
  delete naming it finds it;
- ``sync()``: a listing loads every file no served map came from, and drops the maps whose
  file is gone;
- ``drop_if_gone(m)``: a served map whose file was deleted from the directory (by another
  replica) is no longer served (``MapAdmin.refresh`` and ``sync``).

A file that cannot be loaded (half-copied by hand, damaged, another map's name) is logged once
per version of the file (its size and modification time) and tried again when it changes.
Temporary files (uploads being staged) never have the ``.swmap`` suffix and are not looked at.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from service.maps.route_map import SUFFIX, MapError, RouteMap, list_maps, load_map

if TYPE_CHECKING:
    from service.settings import Settings

log = logging.getLogger("swarmloc")


class FollowerHost(Protocol):
    """What the follower needs of the map admin that owns it (``MapAdmin``)."""

    @property
    def directory(self) -> Path: ...
    @property
    def settings(self) -> Settings: ...
    def served(self) -> dict[str, RouteMap]: ...
    def own_file(self, m: RouteMap) -> Path | None: ...
    def register(self, m: RouteMap, source: str) -> bool: ...


class DirectoryFollower:
    """The maps of a shared directory that this service serves (module docstring). The
    caller holds the admin's lock around every call."""

    def __init__(self, host: FollowerHost) -> None:
        self.host = host
        self._refused: dict[str, tuple[int, int]] = {}  # file name -> (size, mtime) refused

    def drop_if_gone(self, m: RouteMap) -> bool:
        """Stop serving ``m`` when its file in the maps directory no longer exists (deleted
        through another service); whether it was dropped."""
        own = self.host.own_file(m)
        if own is None or own.exists():
            return False
        self.host.served().pop(m.name, None)
        log.info("map %s: its file %s is gone from the maps directory (deleted through "
                 "another service); no longer served", m.name, own.name)
        return True

    def discover(self, name: str) -> RouteMap | None:
        """Map ``name`` (a valid map name: ``MapAdmin.discover`` checks it) from the file
        ``NAME.swmap`` another service wrote; None where there is no such file or it cannot
        be served."""
        path = self.host.directory / f"{name}{SUFFIX}"
        if not path.is_file() or path.name in self._files():
            return None  # none, or the file of a map served under the name in its header
        return self._adopt(path, name)

    def _files(self) -> set[str]:
        """The names of the directory's files that served maps came from."""
        return {own.name for own in map(self.host.own_file, self.host.served().values())
                if own is not None}

    def sync(self) -> None:
        """Load the directory's map files that no served map came from; drop the served maps
        whose file is gone."""
        for m in list(self.host.served().values()):
            self.drop_if_gone(m)
        known = self._files()
        for path in list_maps(self.host.directory):
            if path.name not in known:
                self._adopt(path, None)

    def _adopt(self, path: Path, name: str | None) -> RouteMap | None:
        """Load ``path`` and serve it (``name``: the name its header must carry)."""
        try:
            st = path.stat()
        except OSError:
            return None
        stamp = (st.st_size, st.st_mtime_ns)
        if self._refused.get(path.name) == stamp:
            return None
        try:
            m = load_map(path, verify="lazy", matcher=self.host.settings.matcher)
            if name is not None and m.name != name:
                raise MapError(f"{path}: holds map '{m.name}', not '{name}'")
            if m.name in self.host.served():
                raise MapError(f"{path}: map '{m.name}' is already served from another file")
        except (OSError, ValueError) as exc:  # MapError is a ValueError
            self._refused[path.name] = stamp
            log.warning("map file %s in the maps directory not served: %s", path.name, exc)
            return None
        self._refused.pop(path.name, None)
        self.host.register(m, "directory")
        log.info("map %s: served from %s (written by another service on the maps directory)",
                 m.name, path.name)
        return m
