"""Map lifecycle without a restart: upload, replace, delete, and build jobs with progress.

Versions: a map's version is its file checksum (SHA-256 of header and data), sent as the
``ETag``. ``If-Match`` (a list of versions, or ``*``: the map exists) and ``If-None-Match``
(``*``: the map does not exist yet) are checked under one lock together with the rename, so
two fleet tools never overwrite each other's map unnoticed (412).

Uploads are staged in a hidden temporary file in the maps directory, verified with
``load_map(verify=True)`` (magic, version, layout, checksum, consistent arrays), then renamed
over the old file (same filesystem: atomic) and registered. A replaced map stays memory-mapped
by the sessions that run on it (the old inode lives until they let go); new sessions get the
new version, and ``reset`` moves a session to it.

Builds: the archive is extracted and validated before the job is accepted (bad input: 4xx at
once, nothing left behind). One worker thread builds one map at a time; after each image it
sleeps so that it works at most ``build_duty`` of the time, leaving the CPU to robots' frames.
The map is built in memory, saved atomically and only then registered: never half-built.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import queue
import re
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Protocol, cast

import numpy as np

from service.api.errors import (
    BadRequest,
    Conflict,
    InsufficientStorage,
    InvalidParameters,
    NotFound,
    PayloadTooLarge,
    PreconditionFailed,
    ServiceError,
    Unavailable,
)
from service.api.models import (
    DEFAULT_FEATURES,
    FeatureTypeName,
    JobInfo,
    JobState,
    MapDeleted,
    MapSummary,
)
from service.engine.duty import rest
from service.engine.map_mirror import MAX_MIRRORED_BYTES, MapMirror
from service.engine.shared_maps import DirectoryFollower
from service.maps.experiences import (
    NewImage,
    add_experience,
    base_identity,
    budget_bytes,
    carry_geometry,
    experience_layers,
    remove_experience,
)
from service.maps.round_archive import ArchiveLimits, UploadedRound, extract_round, remove_tree
from service.maps.route_map import (
    SUFFIX,
    WRITE_TEMPS,
    MapError,
    RouteMap,
    build_map_from_rounds,
    file_version,
    load_map,
    save_map,
)
from service.vision.features import FEATURE_TYPES, named_params, sift_cap

if TYPE_CHECKING:
    from service.engine.learning import Learner
    from service.engine.metrics import Metrics
    from service.settings import Settings
    from service.vision.features import FeatureParams


class MapHost(Protocol):
    """What map admin needs of the service that serves the maps (``LocalizationService``)."""

    settings: Settings
    metrics: Metrics
    maps: dict[str, RouteMap]
    load_errors: dict[str, str]
    learner: Learner

    def get_map(self, name: str) -> RouteMap: ...
    def adopt(self, m: RouteMap) -> None: ...
    def map_summary(self, name: str) -> MapSummary: ...
    def sessions_on_map(self, name: str) -> list[str]: ...
    def delete_session(self, robot_id: str) -> None: ...

log = logging.getLogger("swarmloc")
TEMP_PREFIX = ".swarmloc-"  # hidden and without the .swmap suffix: never loaded as a map
_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}")
_KEEP_JOBS = 100
STALE_S = 24 * 3600.0
WRITABLE_TRUST_S = 10.0  # a maps directory found writable is not probed again meanwhile


def check_map_name(name: str) -> None:
    if not _NAME.fullmatch(name or ""):
        raise InvalidParameters(f"map name '{name}' must be 1-64 letters, digits, '-', '_' or "
                                "'.', not starting with '.'")


def _tags(header: str | None) -> list[str] | None:
    """Entity tags of an If-Match / If-None-Match header (quotes and W/ dropped)."""
    if header is None:
        return None
    return [t.strip().removeprefix("W/").strip('"') for t in header.split(",") if t.strip()]


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


_FULL = (errno.ENOSPC, errno.EDQUOT)
_NOT_WRITABLE = (errno.EROFS, errno.EACCES, errno.EPERM)


def _storage_fault(exc: OSError) -> tuple[type[ServiceError], str] | None:
    """The error class and what is wrong, for an OSError of a full (507) or unwritable (503)
    maps directory; None for any other OSError. No path."""
    reason = os.strerror(exc.errno) if exc.errno is not None else type(exc).__name__
    if exc.errno in _FULL:
        return InsufficientStorage, f"no space left in the maps directory ({reason})"
    if exc.errno in _NOT_WRITABLE:
        return Unavailable, f"the maps directory is not writable by the service ({reason})"
    return None


def storage_error(exc: OSError, name: str, what: str) -> ServiceError | None:
    """A write into the maps directory that failed as the error a client is told: 507 when
    the disk (or the service's quota) is full, 503 when the directory is read-only or not
    the service's to write; None for any other OSError. No path: only the map's name."""
    fault = _storage_fault(exc)
    if fault is None:
        return None
    kind, problem = fault
    retry = "; retry when space is freed" if kind is InsufficientStorage else ""
    return kind(f"map '{name}': {what} failed: {problem}; the map and its sessions are "
                f"unchanged{retry}")


@contextlib.contextmanager
def writing(name: str, what: str) -> Iterator[None]:
    """Writes of map ``name`` into the maps directory: an OSError of a full or unwritable
    directory becomes ``storage_error`` (one warning line in the log, no traceback)."""
    try:
        yield
    except OSError as exc:
        err = storage_error(exc, name, what)
        if err is None:
            raise
        log.warning("map %s: %s failed: %s", name, what, exc)
        raise err from None


@dataclass
class Job:
    id: str
    map: str
    round: UploadedRound
    workdir: Path
    if_match: str | None
    if_none_match: str | None
    features: FeatureTypeName
    params: FeatureParams  # the features' settings (``build_params``)
    state: JobState = "queued"
    done: int = 0
    error: str | None = None
    status: int | None = None
    checksum: str | None = None
    created: float = field(default_factory=time.time)
    started: float | None = None
    finished: float | None = None

    def info(self) -> JobInfo:
        return JobInfo(id=self.id, map=self.map, state=self.state, done=self.done,
                       total=len(self.round), error=self.error, status=self.status,
                       checksum=self.checksum, features=self.features,
                       max_features=sift_cap(self.params), width=self.params.width,
                       height=self.params.height, created=self.created,
                       started=self.started,
                       finished=self.finished)


class MapAdmin:
    """Map upload / replace / delete and the build queue of one service."""

    def __init__(self, service: MapHost) -> None:
        self.service = service
        self.settings = service.settings
        self._lock = threading.RLock()  # preconditions + rename + register, delete
        self._jobs: dict[str, Job] = {}
        self._queue: queue.Queue[Job] = queue.Queue()
        self._worker: threading.Thread | None = None
        self.follower = DirectoryFollower(self)  # maps other services on the directory wrote
        self.mirror: MapMirror | None = None  # maps through Redis (settings.maps_sync)
        self._writable_until = 0.0  # time.monotonic() until which a probe is trusted
        self.remove_stale()

    def remove_stale(self, older_than_s: float = STALE_S) -> list[str]:
        """Remove temporary files and folders a crash left in the maps directory (staged
        uploads and builds, and map versions a killed write left half-written; only old
        ones: another service on the same directory may be using fresh ones)."""
        gone: list[str] = []
        if not self.directory.is_dir():
            return gone
        limit = time.time() - older_than_s
        for p in [*self.directory.glob(f"{TEMP_PREFIX}*"), *self.directory.glob(WRITE_TEMPS)]:
            try:
                if p.lstat().st_mtime >= limit:
                    continue
                if p.is_dir():
                    remove_tree(p)
                else:
                    p.unlink()
                gone.append(p.name)
            except OSError:
                pass
        return gone

    @property
    def directory(self) -> Path:
        return Path(self.settings.maps_dir)

    def served(self) -> dict[str, RouteMap]:
        return self.service.maps

    def own_file(self, m: RouteMap) -> Path | None:
        """The file ``m`` was loaded from where it lies in this service's maps directory (the
        one file uploads replace, deletes remove and experiences rewrite); None otherwise."""
        return m.path if m.path is not None and m.path.parent == self.directory else None

    # ---- a maps directory shared with other services (service/engine/shared_maps.py) --
    def discover(self, name: str) -> RouteMap | None:
        """Map ``name``, loaded first when another service on the maps directory wrote it;
        None where this service has no such map."""
        if not _NAME.fullmatch(name or ""):
            return None  # never a path: only a map name names a file
        with self._lock:
            if name in self.service.maps:
                return self.service.maps[name]
            self._pull(name)
            return self.follower.discover(name)

    def sync(self) -> list[str]:
        """The names of the maps served, after following the maps directory (maps other
        services added are loaded, those they deleted dropped)."""
        with self._lock:
            if self.mirror is not None:
                for name in sorted(set(self._mirrored_names()) | set(self.service.maps)):
                    self._pull(name)
            self.follower.sync()
            self.service.metrics.maps.set(len(self.service.maps))
            return sorted(self.service.maps)

    # ---- map files through Redis (service/engine/map_mirror.py) ---------------------------
    def attach_mirror(self, mirror: MapMirror) -> None:
        """Share the maps through Redis from now on: the maps this service loaded are brought
        to the versions Redis holds (published first where it holds none; removed where they
        were deleted through another replica), and those only Redis holds are loaded."""
        with self._lock:
            self.mirror = mirror
            for name in list(self.service.maps):
                try:
                    self.refresh(name)
                except NotFound:
                    pass
            self.sync()

    def _mirrored_names(self) -> list[str]:
        assert self.mirror is not None
        try:
            return [n for n in self.mirror.names() if _NAME.fullmatch(n)]
        except self.mirror.errors as exc:
            log.warning("maps in Redis not listed (%s: %s); serving this service's copies",
                        type(exc).__name__, exc)
            return []

    def _pull(self, name: str) -> None:
        """Bring this service's file of map ``name`` to the version Redis holds: fetched
        where it differs, removed after a delete through another replica, published where
        Redis holds none. Redis unavailable: the file stays as it is (logged). The caller
        holds the lock, then reloads or drops the map as for a shared directory."""
        if self.mirror is None or not _NAME.fullmatch(name):
            return
        served = self.service.maps.get(name)
        path = (self.own_file(served) if served is not None else None) or \
            self.directory / f"{name}{SUFFIX}"
        failures: tuple[type[Exception], ...] = (*self.mirror.errors, OSError)
        try:
            head = self.mirror.head(name)
            local = file_version(path) if path.is_file() else None
            if head is None:
                if local is not None:
                    self.mirror.publish(name, path, local, None)
            elif head.deleted:
                if path.is_file():
                    path.unlink(missing_ok=True)
                    _fsync_dir(path.parent)
                    log.info("map %s: deleted through another replica; %s removed", name,
                             path.name)
            elif head.version != local:
                self._fetch(name, path, head.version)
        except failures as exc:
            log.warning("map %s: not compared with the maps in Redis (%s: %s); serving this "
                        "service's copy", name, type(exc).__name__, exc)

    def _fetch(self, name: str, path: Path, version: str) -> None:
        """The published file of map ``name`` (``version``), verified, renamed over
        ``path``."""
        assert self.mirror is not None
        self.directory.mkdir(parents=True, exist_ok=True)
        tmp = self.mirror.fetch(name, self.directory, TEMP_PREFIX)
        if tmp is None:
            return
        try:
            got = file_version(tmp)
            if got != version:
                log.warning("map %s: the file in Redis holds version %s, not %s; not taken",
                            name, got, version)
                return
            try:  # checked whole (its checksum) before it replaces this service's copy
                load_map(tmp, verify=True, matcher="exact")
            except MapError as exc:
                log.warning("map %s: the file in Redis is damaged, not taken: %s", name,
                            str(exc).replace(str(tmp), "the file in Redis"))
                return
            os.replace(tmp, path)
            _fsync_dir(path.parent)
            log.info("map %s: version %s taken from Redis into %s", name, version[:12],
                     path.name)
        finally:
            tmp.unlink(missing_ok=True)

    def _publish(self, name: str, path: Path, version: object, base: str | None) -> None:
        """Publish a new version of map ``name`` written from version ``base`` (None: none);
        412 where another replica published another version meanwhile, 503 where Redis is
        unavailable (then nothing is published: this service's file goes back to the
        published version at its next look)."""
        if self.mirror is None:
            return
        if not isinstance(version, str):
            raise MapError(f"map '{name}' has no checksum to publish")
        size = path.stat().st_size
        if size > MAX_MIRRORED_BYTES:
            raise PayloadTooLarge(f"map '{name}' is {size} bytes; maps shared through Redis "
                                  f"(SWARMLOC_MAPS_SYNC=redis) take at most "
                                  f"{MAX_MIRRORED_BYTES} bytes (Redis's largest value)")
        mirror = self.mirror
        self._compare_and_set(name, base, "written",
                              lambda: mirror.publish(name, path, version, base))

    def _tombstone(self, name: str, base: str | None) -> None:
        """Publish the delete of map ``name`` at version ``base`` (412 / 503 as
        ``_publish``)."""
        if self.mirror is not None:
            mirror = self.mirror
            self._compare_and_set(name, base, "deleted", lambda: mirror.delete(name, base))

    def _compare_and_set(self, name: str, base: str | None, what: str,
                         change: Callable[[], bool]) -> None:
        """One compare-and-set of what Redis holds of map ``name`` (``change``): 503 where
        Redis is unavailable, 412 where it no longer holds version ``base``."""
        assert self.mirror is not None
        try:
            ok = change()
        except self.mirror.errors as exc:
            raise Unavailable(f"map '{name}' not {what}: the maps in Redis are unavailable "
                              f"({type(exc).__name__}: {exc}); retry shortly") from None
        if not ok:
            raise PreconditionFailed(
                f"map '{name}' was changed through another replica meanwhile (no longer at "
                f"version {base}); fetch GET /maps/{name} and retry with its ETag")

    @contextlib.contextmanager
    def _file_lock(self, path: Path) -> Iterator[None]:
        """An exclusive lock on map file ``path`` across every process on this maps
        directory (its hidden lock file): one writer at a time, and a precondition checked
        against the version on disk stays true until the rename."""
        fd = os.open(path.with_name(f".{path.name}.lock"), os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            yield
        finally:
            os.close(fd)  # releases the lock

    # ---- versions -----------------------------------------------------------------------
    def check_preconditions(self, name: str, if_match: str | None,
                            if_none_match: str | None) -> str | None:
        """Against the newest version on disk (another service on the maps directory may
        have written it); returns that version (None: no such map)."""
        try:
            current, exists = self.refresh(name).meta.get("checksum"), True
        except NotFound:
            current, exists = None, False
        wanted = _tags(if_match)
        if wanted is not None and not (exists and ("*" in wanted or current in wanted)):
            raise PreconditionFailed(
                f"If-Match: map '{name}' is " + (f"at version {current}" if exists else
                                                 "not loaded") + "; someone changed it, fetch "
                "GET /maps/{name} and retry with its ETag")
        avoid = _tags(if_none_match)
        if avoid is not None and exists and ("*" in avoid or current in avoid):
            raise PreconditionFailed(f"If-None-Match: map '{name}' already exists (version "
                                     f"{current}); replace it with If-Match instead")
        return current if isinstance(current, str) else None

    def probe_writable(self) -> None:
        """The OSError of a maps directory this service cannot write, if it is one: a hidden
        temporary file created and removed (``TEMP_PREFIX``: were one ever left behind,
        ``remove_stale`` removes it)."""
        fd, path = tempfile.mkstemp(prefix=f"{TEMP_PREFIX}probe-", dir=self.directory)
        os.close(fd)
        os.unlink(path)

    def check_learnable(self, m: RouteMap) -> None:
        """Before a learning session on map ``m`` is created: 503 where the maps directory
        holding its file is not writable by the service (read-only, not permitted), whose
        every learned batch would otherwise fail into the log; 507 where it cannot take even
        an empty file. One probe (``probe_writable``); a success is trusted for
        ``WRITABLE_TRUST_S``, so a fleet starting its learning sessions writes one temporary
        file, not one per robot."""
        name = m.name
        if self.own_file(m) is None or time.monotonic() < self._writable_until:
            return
        try:
            self.probe_writable()
        except OSError as exc:
            fault = _storage_fault(exc)
            if fault is None:
                raise
            kind, problem = fault
            log.warning("map %s: a learning session refused: %s", name, exc)
            raise kind(f"map '{name}' cannot learn: {problem}, so what a learning session "
                       "teaches could not be written; create the session without learn, or "
                       "make the maps directory writable") from None
        self._writable_until = time.monotonic() + WRITABLE_TRUST_S

    # ---- uploads ------------------------------------------------------------------------
    def staging_file(self, kind: str) -> Path:
        """A new hidden temporary file in the maps directory (removed by the caller)."""
        self.directory.mkdir(parents=True, exist_ok=True)
        fd, path = tempfile.mkstemp(prefix=f"{TEMP_PREFIX}{kind}-", suffix=".part",
                                    dir=self.directory)
        os.close(fd)
        return Path(path)

    def install_upload(self, name: str, staged: Path, if_match: str | None = None,
                       if_none_match: str | None = None) -> tuple[MapSummary, bool]:
        """Verify a staged .swmap, rename it into place and load it; True when created.

        The staged file is gone afterwards, whatever happened.
        """
        metrics = self.service.metrics
        try:
            check_map_name(name)
            try:
                m = load_map(staged, verify=True, matcher=self.service.settings.matcher)
            except MapError as exc:
                metrics.map_loads.labels("upload", "failed").inc()
                raise BadRequest(str(exc).replace(str(staged), "uploaded map")) from None
            if m.name != name:
                raise InvalidParameters(
                    f"the uploaded map is named '{m.name}' in its header, not '{name}'; upload "
                    f"it to /maps/{m.name} or rebuild it under the name '{name}'")
            with writing(name, "the upload"):
                with staged.open("rb+") as fh:
                    os.fsync(fh.fileno())
                staged.chmod(0o644)  # mkstemp made it private; maps are readable as save_map's
                with self._lock:
                    final = self._file_of(name)
                    with self._file_lock(final):
                        base = self.check_preconditions(name, if_match, if_none_match)
                        self._publish(name, staged, m.meta.get("checksum"), base)
                        os.replace(staged, final)
                        _fsync_dir(final.parent)
                        m.path = final
                        created = self.register(m, "upload")
        except ServiceError:
            metrics.map_uploads.labels("rejected").inc()
            raise
        finally:
            staged.unlink(missing_ok=True)
        metrics.map_uploads.labels("created" if created else "replaced").inc()
        return self.service.map_summary(name), created

    def _file_of(self, name: str) -> Path:
        old = self.service.maps.get(name)
        own = self.own_file(old) if old is not None else None
        if own is not None:
            return own  # replace the file it was loaded from (its name may differ)
        path = self.directory / f"{name}{SUFFIX}"
        other = [m.name for m in self.service.maps.values() if m.path == path]
        if other:
            raise Conflict(f"{path.name} holds the loaded map '{other[0]}'; delete that map "
                           f"first or use another name than '{name}'")
        return path

    def register(self, m: RouteMap, source: str) -> bool:
        created = m.name not in self.service.maps
        old = self.service.maps.get(m.name)
        if old is not None and old is not m:  # a version with new experiences: what the old
            carry_geometry(old, m)  # one has built of the images both hold is kept
        self.service.maps[m.name] = m
        self.service.adopt(m)
        self.service.load_errors.pop(m.path.name if m.path else "", None)
        self.service.metrics.map_loads.labels(source, "ok").inc()
        self.service.metrics.maps.set(len(self.service.maps))
        return created

    def open_file(self, name: str) -> tuple[object, str, int]:
        """An open binary file of the current version of a map, its ETag and size."""
        with self._lock:
            m = self.service.get_map(name)
            if m.path is None:
                raise NotFound(f"map '{name}' has no file on this service")
            fh = m.path.open("rb")
            return fh, m.meta.get("checksum", ""), os.fstat(fh.fileno()).st_size

    # ---- delete -------------------------------------------------------------------------
    def delete(self, name: str, force: bool = False, if_match: str | None = None
               ) -> MapDeleted:
        """Delete map ``name``: its file first, so that a maps directory the service cannot
        write (503) leaves the map and its sessions as they were."""
        with self._lock, contextlib.ExitStack() as held:
            m = self.service.get_map(name)
            own = self.own_file(m)
            if own is not None:
                with writing(name, "the delete"):
                    held.enter_context(self._file_lock(own))
            base = self.check_preconditions(name, if_match, None)
            users = self.service.sessions_on_map(name)
            if users and not force:
                raise Conflict(f"map '{name}' is used by {len(users)} session(s): "
                               f"{', '.join(users)}; delete or move them first, or send "
                               "?force=true to end them")
            if own is not None:  # before the delete is published to other replicas
                with writing(name, "the delete"):
                    self.probe_writable()
            self._tombstone(name, base)
            if own is not None:
                with writing(name, "the delete"):
                    own.unlink(missing_ok=True)
                    _fsync_dir(self.directory)
            for robot_id in users:
                try:
                    self.service.delete_session(robot_id)
                except NotFound:
                    pass
            del self.service.maps[name]
            self.service.metrics.maps.set(len(self.service.maps))
            self.service.metrics.map_deletes.inc()
        return MapDeleted(map=name, ended_sessions=users)

    # ---- experiences (service/maps/experiences.py) ----------------------------------------
    def _writable(self, m: RouteMap) -> Path:
        own = self.own_file(m)
        if own is None:
            raise Conflict(f"map '{m.name}' has no file in this service's maps directory; its "
                           "experiences cannot be written")
        return own

    def refresh(self, name: str) -> RouteMap:
        """The loaded map ``name``, first reloaded when its file holds another version (one
        that another replica on the same maps directory wrote); a header read. A map whose
        file another replica deleted is no longer served (NotFound)."""
        with self._lock:
            m = self.service.get_map(name)
            self._pull(name)
            own = self.own_file(m)
            if own is None:
                return m
            if self.follower.drop_if_gone(m):
                self.service.metrics.maps.set(len(self.service.maps))
                raise NotFound(f"map '{name}' was deleted: its file {own.name} is gone from "
                               "the maps directory")
            on_disk = file_version(own)
            if on_disk is None or on_disk == m.meta.get("checksum"):
                return m
            try:
                new = load_map(own, verify="lazy", matcher=m.matcher)
            except MapError as exc:  # half-seen or broken: keep serving the loaded version
                log.warning("map %s: newer file not loaded: %s", name, exc)
                return m
            if new.name == name:
                self.register(new, "reload")
                return new
            return m

    @contextlib.contextmanager
    def _writer(self, name: str) -> Iterator[RouteMap]:
        """The one writer of map ``name`` across every process on this maps directory (an
        exclusive lock on its lock file), with the map at its newest version on disk."""
        with self._lock:
            path = self._writable(self.service.get_map(name))
            with self._file_lock(path):
                yield self.refresh(name)

    def commit_experience(self, name: str, exp_id: str, images: list[NewImage],
                          condition: str | None, robot: str, base: str | None = None) -> None:
        """Write a learning session's images into experience ``exp_id`` of map ``name``: a new
        version (retiring the least used experiences beyond the budget). Called by the
        background writer (service/engine/experience_writer.py), never on a frame's path;
        raises when the map cannot take them (the writer logs it, the map keeps serving).
        ``base``: the ``base_identity`` of the map they were learned on; a map rebuilt or
        replaced under the name since (another identity) does not take them (409)."""
        try:
            with self._writer(name) as m:
                if base is not None and base != base_identity(m):
                    raise Conflict(f"map '{name}' was replaced (rebuilt or uploaded) since "
                                   "these images were learned on it: their positions are "
                                   "not the new map's; the robot's next images after its "
                                   "reset teach it")
                usage = self.service.learner.usage(name, clear=True)
                new, retired = m, list[str]()
                try:
                    new, retired = add_experience(
                        m, self._writable(m), exp_id, images, condition=condition,
                        robot=robot, now=time.time(),
                        budget_bytes=budget_bytes(self.settings.experience_budget_mb),
                        usage=usage)
                finally:
                    if new is m:  # nothing written: the uses wait for the next write
                        self.service.learner.restore_usage(name, usage)
                if new is not m:
                    assert new.path is not None
                    self._publish(name, new.path, new.meta.get("checksum"),
                                  m.meta.get("checksum"))
                    self.register(new, "experience")
        except Exception:
            self.service.metrics.map_loads.labels("experience", "failed").inc()
            raise
        if retired:
            log.info("map %s: experiences %s retired (budget)", name, ", ".join(retired))

    def delete_experience(self, name: str, exp_id: str, if_match: str | None = None
                          ) -> MapSummary:
        """Remove one experience of a map (a new version)."""
        with writing(name, f"removing experience '{exp_id}'"), self._writer(name) as m:
            self.check_preconditions(name, if_match, None)
            if exp_id not in experience_layers(m):
                raise NotFound(f"map '{name}' has no experience '{exp_id}'; it has "
                               f"{sorted(experience_layers(m))}")
            usage = self.service.learner.usage(name, clear=True)
            try:
                new = remove_experience(m, self._writable(m), exp_id, usage)
            except BaseException:  # nothing written: the uses wait for the next write
                self.service.learner.restore_usage(name, usage)
                raise
            assert new.path is not None
            self._publish(name, new.path, new.meta.get("checksum"), m.meta.get("checksum"))
            self.register(new, "experience")
        return self.service.map_summary(name)

    # ---- builds -------------------------------------------------------------------------
    def limits(self) -> ArchiveLimits:
        s = self.settings
        return ArchiveLimits(s.max_archive_members, s.max_unpacked_bytes, s.max_archive_ratio,
                             s.max_pixels)

    def submit_build(self, name: str, archive: Path, if_match: str | None = None,
                     if_none_match: str | None = None,
                     features: str = DEFAULT_FEATURES,
                     max_features: int | None = None, width: int | None = None,
                     height: int | None = None) -> JobInfo:
        """Extract and validate a round archive, queue its build with the feature type
        ``features`` at the working size ``width`` x ``height`` (SIFT keeping
        ``max_features`` per image; None: the type's defaults); the archive is removed."""
        metrics = self.service.metrics
        workdir: Path | None = None
        try:
            check_map_name(name)
            if features not in FEATURE_TYPES:
                raise BadRequest(f"unknown feature type '{features[:40]}'; choose one of "
                                 f"{', '.join(FEATURE_TYPES)}")
            params = build_params(features, max_features, width, height)
            self.check_preconditions(name, if_match, if_none_match)
            with writing(name, "unpacking the round archive"):
                workdir = Path(tempfile.mkdtemp(prefix=f"{TEMP_PREFIX}build-",
                                                dir=self.directory))
                rnd = extract_round(archive, workdir / "round", self.limits())
        except ServiceError:
            metrics.map_builds.labels("rejected").inc()
            if workdir is not None:
                remove_tree(workdir)
            raise
        except BaseException:
            if workdir is not None:
                remove_tree(workdir)
            raise
        finally:
            archive.unlink(missing_ok=True)
        job = Job(uuid.uuid4().hex[:12], name, rnd, workdir, if_match, if_none_match,
                  cast(FeatureTypeName, features), params)
        with self._lock:
            self._jobs[job.id] = job
            self._trim_jobs()
            if self._worker is None or not self._worker.is_alive():
                self._worker = threading.Thread(target=self._work, name="map-builder",
                                                daemon=True)
                self._worker.start()
        self._queue.put(job)
        metrics.map_builds.labels("submitted").inc()
        return job.info()

    def job(self, job_id: str) -> JobInfo:
        try:
            return self._jobs[job_id].info()
        except KeyError:
            raise NotFound(f"no job '{job_id}' (the last {_KEEP_JOBS} jobs are kept)") from None

    def jobs(self) -> list[JobInfo]:
        return [j.info() for j in sorted(self._jobs.values(), key=lambda j: j.created)]

    def _trim_jobs(self) -> None:
        finished = [j for j in self._jobs.values() if j.state in ("done", "failed")]
        for j in sorted(finished, key=lambda j: j.created)[:max(0, len(self._jobs) - _KEEP_JOBS)]:
            del self._jobs[j.id]

    def _work(self) -> None:
        while True:
            job = self._queue.get()
            try:
                self._build(job)
            finally:
                remove_tree(job.workdir)
                self._queue.task_done()

    def _paced_images(self, job: Job) -> Iterator[np.ndarray]:
        """The round's images, counting progress and sleeping to keep to the duty cycle."""
        duty = self.settings.build_duty
        for i in range(len(job.round)):
            t0 = time.perf_counter()
            yield job.round.load_image(i)  # resumes once build_map extracted its features
            job.done = i + 1
            rest(t0, duty)

    def _build(self, job: Job) -> None:
        metrics = self.service.metrics
        job.state, job.started = "running", time.time()
        rnd = job.round
        try:
            m = build_map_from_rounds([rnd], name=job.map, images=self._paced_images(job),
                                      params=job.params,
                                      source={"name": rnd.name, "uploaded": True, "job": job.id})
            with self._lock, writing(job.map, "the build"):
                target = self._file_of(job.map)
                with self._file_lock(target):
                    base = self.check_preconditions(job.map, job.if_match, job.if_none_match)
                    final = save_map(m, target)
                    try:
                        loaded = load_map(final, verify=True,
                                          matcher=self.service.settings.matcher)
                    except MapError:
                        metrics.map_loads.labels("build", "failed").inc()
                        raise
                    self._publish(job.map, final, loaded.meta.get("checksum"), base)
                    self.register(loaded, "build")
            job.checksum = loaded.meta.get("checksum")
            job.state = "done"
            metrics.map_builds.labels("done").inc()
        except ServiceError as exc:
            job.state, job.error, job.status = "failed", exc.message, exc.status
        except Exception as exc:  # a failed build never takes the worker down
            job.state, job.error, job.status = "failed", f"{type(exc).__name__}: {exc}", 500
        finally:
            job.finished = time.time()
            metrics.map_build_seconds.observe(job.finished - job.started)
            if job.state == "failed":
                metrics.map_builds.labels("failed").inc()


def payload_to_file(admin: MapAdmin, data: bytes, kind: str, limit: int, name: str) -> Path:
    """Stage an in-memory payload (Zenoh) for map ``name`` like an HTTP body: size limit,
    hidden temp file, 503 / 507 where the maps directory cannot take it."""
    if len(data) > limit:
        raise PayloadTooLarge(f"{kind} is {len(data)} bytes; the limit is {limit} bytes")
    with writing(name, f"receiving the {'map' if kind == 'upload' else 'round archive'}"):
        path = admin.staging_file(kind)
        try:
            with path.open("wb") as fh:
                fh.write(data)
        except BaseException:
            path.unlink(missing_ok=True)
            raise
    return path


def build_params(features: str, max_features: int | None, width: int | None,
                 height: int | None) -> FeatureParams:
    """A build's feature parameters (``named_params``; None: the type's default size or
    cap), BadRequest naming what is out of range (the transports check the types)."""
    size = {k: v for k, v in (("width", width), ("height", height)) if v is not None}
    try:
        return named_params(features, max_features=max_features, **size)
    except ValueError as exc:
        raise BadRequest(str(exc)) from None
