"""Session stores: where robot sessions live between frames.

Protocol: a frame holds its robot's lock (``locked``) while the estimator steps; the state
the block leaves is stored when it ends without an error, before the answer goes out. The
stores that keep a copy (SQLite, Redis) drop a failed block's half-changed object and read
the stored state back next time; they cache the live Session objects and decode a stored
blob (service/engine/state_codec.py) only on a miss, and a write is a compare-and-set on the
version it loaded, so a frame on a session replaced or deleted meanwhile is refused (409).

- ``SqliteStore`` (default, ``SWARMLOC_SESSION_STORE=sqlite`` or ``sqlite:///PATH``;
  service/engine/sqlite_store.py): one row per robot ``(robot_id, version, map, last_used,
  state)`` in a SQLite file in WAL mode held by this one process. Each applied frame,
  create, reset and delete is one committed statement (a frame: one encode, one UPDATE).
  With ``synchronous=NORMAL`` a commit survives a crash of the process (kill -9), so a
  restart resumes every robot at its last applied frame.
- ``InProcessStore`` (``SWARMLOC_SESSION_STORE=memory``): live objects in this process only
  (lost on a crash). With ``SWARMLOC_SESSION_SNAPSHOT=PATH`` a clean shutdown writes every
  session to PATH (atomically: temp file, fsync, rename) and the next start reads it back
  (checksum verified) and deletes it, so a later crash cannot roll sessions back to an old
  snapshot.
- ``RedisStore`` (``SWARMLOC_SESSION_STORE=redis://host:port/db``): every session is a Redis
  hash ``{v: version, st: state blob, map: name}`` shared by any
  number of replicas. A frame takes the robot's lock (a lease: ``SET NX PX`` with a random
  token), loads the state, steps it and writes it back only if the version is still the one
  it loaded (compare-and-set in one Lua script that also releases the lock). So two frames of
  one robot never step the same state, a crashed holder's lock expires after its lease, and
  a frame whose lease ran out while another replica went ahead is refused (409), never
  applied twice. Idle sessions expire with Redis TTLs; a sorted set of robot ids by last use
  makes the session limit fleet-wide. Each replica keeps the last state it decoded per robot
  and skips decoding when Redis still holds that version (a robot that sticks to one replica
  costs two round trips per frame and no decoding).
"""

from __future__ import annotations

import contextlib
import logging
import os
import secrets
import struct
import threading
import time
import zlib
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import msgpack

from service.api.errors import Conflict, NotFound, ServiceError, Unavailable, UnreadableSession
from service.api.models import EstimatorName, SessionInfo
from service.engine.state_codec import SessionState, StateError, decode_session, encode_session
from service.maps.route_map import RouteMap

log = logging.getLogger("swarmloc")

# (map name, checksum, strict) -> the loaded map; strict: the checksum must match
MapResolver = Callable[[str, "str | None", bool], RouteMap]


@dataclass
class Session(SessionState):
    """A robot's session as the service works on it."""

    lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)
    version: str | None = None  # the store's version of this state (Redis)
    map_changed: bool = False  # loaded onto a newer version of its map (only for a reset)

    def info(self) -> SessionInfo:
        loc = self.localizer
        return SessionInfo(robot_id=self.robot_id, map=loc.map.name,
                           estimator=cast(EstimatorName, loc.estimator_name), seed=loc.seed,
                           params=loc.params,
                           frames=loc.seq, created=self.created, last_used=self.last_used,
                           last_estimate=loc.last, map_checksum=loc.map.meta.get("checksum"),
                           learn=self.learn, condition=self.condition)


def robot_lock(locks: dict[str, threading.Lock], guard: threading.Lock, robot_id: str
               ) -> threading.Lock:
    """The robot's lock in ``locks`` (made on first use, under ``guard``): this process's
    frames of one robot queue on it before they go to a shared store."""
    with guard:
        lock = locks.get(robot_id)
        if lock is None:
            lock = locks[robot_id] = threading.Lock()
        return lock


class SessionLimit(Exception):
    """The store holds its limit of sessions."""


class SessionStore(ABC):
    """What the service needs from a place that keeps sessions."""

    shared = False  # several replicas see the same sessions

    @abstractmethod
    def get(self, robot_id: str) -> Session | None:
        """The robot's session as last stored (for reading), or None."""

    @abstractmethod
    def create(self, session: Session, replace: bool, max_sessions: int
               ) -> tuple[Session, bool]:
        """Store a new session; (the stored session, True if created). Without ``replace``
        an existing session is kept and returned. Raises SessionLimit."""

    @abstractmethod
    def delete(self, robot_id: str) -> bool:
        """Remove the session; False if there was none."""

    @abstractmethod
    def __len__(self) -> int:
        """The number of live sessions."""

    @abstractmethod
    def ids(self) -> list[str]:
        """Robot ids of the live sessions."""

    @abstractmethod
    def maps_of(self) -> dict[str, str]:
        """Robot id -> map name of every live session."""

    @abstractmethod
    def locked(self, robot_id: str, strict_map: bool = True
               ) -> contextlib.AbstractContextManager[Session]:
        """The robot's session, held exclusively (fleet-wide for a shared store) while the
        block runs; what the block changed is stored when it ends without an exception, and
        dropped otherwise. NotFound without a session, Conflict when another holder keeps
        it beyond the wait."""

    @abstractmethod
    def expire(self, idle_s: float, now: float) -> list[str]:
        """End sessions idle for more than ``idle_s``; their robot ids."""

    def claim(self, robot_id: str) -> bool:
        """Whether this replica serves the robot's Zenoh traffic (always, unshared)."""
        return True

    def peek(self, robot_id: str) -> Session | None:
        """The session as this replica last saw it, for decisions that do not change it
        (which worker pool a frame goes to); no round trip where a copy is at hand."""
        return self.get(robot_id)

    def close(self) -> None:  # noqa: B027 (optional for a store)
        """Release resources (and write a snapshot where configured)."""


def encode_stored(s: Session) -> bytes:
    """The session's state blob, or a 500 naming what cannot be stored."""
    try:
        return encode_session(s)
    except StateError as exc:
        raise ServiceError(f"cannot store the session of robot '{s.robot_id}': {exc}"
                           ) from None


def decode_stored(robot_id: str, version: str, blob: bytes, resolve: MapResolver,
                  strict: bool) -> Session:
    """A stored session back as a Session. With ``strict`` its map must be the loaded version
    (else the resolver's 409 asks for a reset); without, a session on an older version is
    returned with ``map_changed`` set. A blob that cannot be continued: UnreadableSession."""
    changed = False

    def resolve_map(name: str, checksum: str | None) -> RouteMap:
        nonlocal changed
        m = resolve(name, checksum, strict)
        changed = checksum != m.meta.get("checksum")
        return m

    try:
        st = decode_session(blob, resolve_map)
    except StateError as exc:
        raise UnreadableSession(
            f"stored state of robot '{robot_id}' cannot be continued ({exc}); start it "
            f"over with PUT /sessions/{robot_id} or delete it") from None
    return Session(**vars(st), version=version, map_changed=changed)


# ---- in-process ---------------------------------------------------------------------------
SNAPSHOT_MAGIC = b"SWSN"
SNAPSHOT_VERSION = 1
_SNAP_HEADER = struct.Struct("<4sBI")


class InProcessStore(SessionStore):
    def __init__(self, snapshot: Path | None = None) -> None:
        self._sessions: dict[str, Session] = {}
        self._lock = threading.Lock()
        self.snapshot = snapshot

    def get(self, robot_id: str) -> Session | None:
        return self._sessions.get(robot_id)

    def create(self, session: Session, replace: bool, max_sessions: int
               ) -> tuple[Session, bool]:
        with self._lock:
            old = self._sessions.get(session.robot_id)
            if old is not None and not replace:
                return old, False
            if old is None and len(self._sessions) >= max_sessions:
                raise SessionLimit
            self._sessions[session.robot_id] = session
            return session, old is None

    def delete(self, robot_id: str) -> bool:
        with self._lock:
            return self._sessions.pop(robot_id, None) is not None

    def ids(self) -> list[str]:
        return list(self._sessions)

    def maps_of(self) -> dict[str, str]:
        return {rid: s.localizer.map.name for rid, s in list(self._sessions.items())}

    def __len__(self) -> int:
        return len(self._sessions)

    @contextlib.contextmanager
    def locked(self, robot_id: str, strict_map: bool = True) -> Iterator[Session]:
        s = self._sessions.get(robot_id)
        if s is None:
            raise NotFound(f"no session for robot '{robot_id}'")
        with s.lock:
            yield s

    def expire(self, idle_s: float, now: float) -> list[str]:
        with self._lock:
            gone = [rid for rid, s in self._sessions.items() if now - s.last_used > idle_s
                    and not s.lock.locked()]
            for rid in gone:
                del self._sessions[rid]
        return gone

    def close(self) -> None:
        if self.snapshot is not None:
            n = self.save_snapshot(self.snapshot)
            log.info("wrote %d sessions to %s", n, self.snapshot)

    # ---- snapshot ---------------------------------------------------------------------
    def save_snapshot(self, path: Path) -> int:
        """Write every session to ``path`` atomically; the number written."""
        blobs = []
        for s in list(self._sessions.values()):
            with s.lock:
                blobs.append(encode_session(s))
        body = msgpack.packb(blobs, use_bin_type=True)
        data = _SNAP_HEADER.pack(SNAPSHOT_MAGIC, SNAPSHOT_VERSION, zlib.crc32(body)) + body
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
        return len(blobs)

    def load_snapshot(self, path: Path, resolve: MapResolver) -> tuple[int, list[str]]:
        """Restore the sessions of a snapshot and delete it: (restored, problems). A snapshot
        that fails its checks is left in place and nothing is restored from it."""
        data = Path(path).read_bytes()
        if len(data) < _SNAP_HEADER.size:
            raise StateError(f"snapshot {path} is truncated")
        magic, version, crc = _SNAP_HEADER.unpack_from(data)
        body = data[_SNAP_HEADER.size:]
        if magic != SNAPSHOT_MAGIC or version != SNAPSHOT_VERSION:
            raise StateError(f"{path} is not a session snapshot of format {SNAPSHOT_VERSION}")
        if zlib.crc32(body) != crc:
            raise StateError(f"snapshot {path} checksum mismatch (corrupt)")
        problems: list[str] = []
        restored = 0
        for blob in msgpack.unpackb(body, raw=False):
            try:
                st = decode_session(blob, lambda n, c: resolve(n, c, True))
            except (StateError, ServiceError) as exc:
                problems.append(str(exc))
                continue
            self._sessions[st.robot_id] = Session(**vars(st))
            restored += 1
        Path(path).unlink()
        return restored, problems


# ---- Redis --------------------------------------------------------------------------------
_ACQUIRE_LOAD = """
if not redis.call('SET', KEYS[1], ARGV[1], 'NX', 'PX', ARGV[2]) then return {0} end
local v = redis.call('HGET', KEYS[2], 'v')
if not v then return {1} end
if v == ARGV[3] then return {1, v} end
return {1, v, redis.call('HGET', KEYS[2], 'st')}
"""
_LOAD = """
local v = redis.call('HGET', KEYS[1], 'v')
if not v then return {} end
if v == ARGV[1] then return {v} end
return {v, redis.call('HGET', KEYS[1], 'st')}
"""
_SAVE_RELEASE = """
local ok = 0
if redis.call('HGET', KEYS[2], 'v') == ARGV[2] then
  redis.call('HSET', KEYS[2], 'v', ARGV[3], 'st', ARGV[4], 'map', ARGV[5])
  redis.call('PEXPIRE', KEYS[2], ARGV[6])
  redis.call('ZADD', KEYS[3], ARGV[7], ARGV[8])
  ok = 1
end
if redis.call('GET', KEYS[1]) == ARGV[1] then redis.call('DEL', KEYS[1]) end
return ok
"""
RELEASE_LEASE = """  -- a lease (KEYS[1]) is deleted only by its holder (token ARGV[1])
if redis.call('GET', KEYS[1]) == ARGV[1] then return redis.call('DEL', KEYS[1]) end
return 0
"""
_CREATE = """
redis.call('ZREMRANGEBYSCORE', KEYS[2], '-inf', ARGV[9])
local exists = redis.call('EXISTS', KEYS[1]) == 1
if exists and ARGV[8] == '0' then
  return {0, redis.call('HGET', KEYS[1], 'v'), redis.call('HGET', KEYS[1], 'st')}
end
if not exists then
  redis.call('ZREM', KEYS[2], ARGV[6])
  if redis.call('ZCARD', KEYS[2]) >= tonumber(ARGV[7]) then return {-1} end
end
redis.call('DEL', KEYS[1])
redis.call('HSET', KEYS[1], 'v', ARGV[1], 'st', ARGV[2], 'map', ARGV[3])
redis.call('PEXPIRE', KEYS[1], ARGV[4])
redis.call('ZADD', KEYS[2], ARGV[5], ARGV[6])
if exists then return {2} end
return {1}
"""
_CLAIM = """
local cur = redis.call('GET', KEYS[1])
if cur == ARGV[1] then redis.call('PEXPIRE', KEYS[1], ARGV[2]) return 1 end
if not cur then redis.call('SET', KEYS[1], ARGV[1], 'PX', ARGV[2]) return 1 end
return 0
"""


@dataclass(frozen=True)
class RedisOptions:
    idle_s: float = 600.0  # TTL of a session after its last frame
    lock_lease_s: float = 10.0  # a crashed holder's lock expires after this
    lock_wait_s: float = 5.0  # the longest a frame waits for the robot's lock (then 409)
    claim_lease_s: float = 5.0  # Zenoh: a replica serves a robot until this passes unused
    replica_id: str = ""
    key_prefix: str = "swarmloc"
    timeout_s: float = 1.0  # socket timeouts: a Redis that does not answer gives 503s


class RedisStore(SessionStore):
    shared = True

    def __init__(self, url: str, resolve: MapResolver, options: RedisOptions) -> None:
        import redis
        from redis.backoff import NoBackoff
        from redis.retry import Retry

        self._errors: tuple[type[Exception], ...] = (redis.exceptions.RedisError, OSError)
        self.url = url
        self.opt = options
        self.replica_id = options.replica_id or f"{os.uname().nodename}-{os.getpid()}"
        # one retry: a pooled connection that Redis closed (a restart) is replaced at once
        self.r = redis.Redis.from_url(
            url, socket_timeout=options.timeout_s, socket_connect_timeout=options.timeout_s,
            retry=Retry(NoBackoff(), 1), health_check_interval=0)
        self._resolve = resolve
        self._acquire_load = self.r.register_script(_ACQUIRE_LOAD)
        self._load = self.r.register_script(_LOAD)
        self._save_release = self.r.register_script(_SAVE_RELEASE)
        self._release = self.r.register_script(RELEASE_LEASE)
        self._create = self.r.register_script(_CREATE)
        self._claim = self.r.register_script(_CLAIM)
        self._cache: dict[str, Session] = {}
        self._local: dict[str, threading.Lock] = {}
        self._guard = threading.Lock()
        p = options.key_prefix
        self._index = f"{p}:index"
        self._k_session = f"{p}:s:"
        self._k_lock = f"{p}:lock:"
        self._k_claim = f"{p}:claim:"

    # ---- helpers ----------------------------------------------------------------------
    @contextlib.contextmanager
    def _io(self) -> Iterator[None]:
        try:
            yield
        except self._errors as exc:
            raise Unavailable(f"session store unavailable (Redis at {self._where()}): "
                              f"{type(exc).__name__}: {exc}; retry shortly") from None

    def _where(self) -> str:
        kw = self.r.connection_pool.connection_kwargs
        return f"{kw.get('host', '?')}:{kw.get('port', '?')}/{kw.get('db', 0)}"

    def _ttl_ms(self) -> int:
        return max(1, round(self.opt.idle_s * 1000))

    def _local_lock(self, robot_id: str) -> threading.Lock:
        return robot_lock(self._local, self._guard, robot_id)

    def _forget(self, robot_id: str) -> None:
        with self._guard:
            self._cache.pop(robot_id, None)
            self._local.pop(robot_id, None)

    def _decode(self, robot_id: str, version: bytes, blob: bytes, strict: bool) -> Session:
        return decode_stored(robot_id, version.decode(), blob, self._resolve, strict)

    def _materialize(self, robot_id: str, res: list[Any], strict: bool) -> Session | None:
        """A Session from a load script's answer [v] (cached) or [v, blob]. Only sessions on
        the loaded version of their map are cached (the others wait for a reset)."""
        if not res:
            return None
        cached = self._cache.get(robot_id)
        if len(res) == 1:
            if cached is not None and cached.version == res[0].decode():
                return cached
            raise ServiceError("session cache out of step")  # cannot happen: we sent its v
        s = self._decode(robot_id, res[0], res[1], strict)
        if not s.map_changed:
            self._cache[robot_id] = s
        return s

    # ---- the interface ----------------------------------------------------------------
    def peek(self, robot_id: str) -> Session | None:
        cached = self._cache.get(robot_id)
        return cached if cached is not None else self.get(robot_id)

    def get(self, robot_id: str) -> Session | None:
        cached = self._cache.get(robot_id)
        with self._io():
            res = self._load(keys=[self._k_session + robot_id],
                             args=[cached.version if cached and cached.version else ""])
        return self._materialize(robot_id, res, strict=False)

    def create(self, session: Session, replace: bool, max_sessions: int
               ) -> tuple[Session, bool]:
        rid = session.robot_id
        version = secrets.token_hex(8)
        blob = encode_stored(session)
        now = time.time()
        with self._io():
            res = self._create(
                keys=[self._k_session + rid, self._index],
                args=[version, blob, session.localizer.map.name, self._ttl_ms(), now, rid,
                      max_sessions, 1 if replace else 0, now - self.opt.idle_s])
        if res[0] == -1:
            raise SessionLimit
        if res[0] == 0:  # kept the existing one
            s = self._decode(rid, res[1], res[2], strict=False)
            self._cache[rid] = s
            return s, False
        session.version = version
        self._cache[rid] = session
        return session, res[0] == 1

    def delete(self, robot_id: str) -> bool:
        with self._io():
            pipe = self.r.pipeline()
            pipe.delete(self._k_session + robot_id)
            pipe.zrem(self._index, robot_id)
            n, _ = pipe.execute()
        self._forget(robot_id)
        return bool(n)

    def ids(self) -> list[str]:
        with self._io():
            raw = cast(list[bytes], self.r.zrangebyscore(
                self._index, time.time() - self.opt.idle_s, "+inf"))
        return [b.decode() for b in raw]

    def maps_of(self) -> dict[str, str]:
        ids = self.ids()
        with self._io():
            pipe = self.r.pipeline()
            for rid in ids:
                pipe.hget(self._k_session + rid, "map")
            names = pipe.execute()
        return {rid: n.decode() for rid, n in zip(ids, names, strict=True) if n is not None}

    def __len__(self) -> int:
        with self._io():
            return int(cast(int, self.r.zcount(self._index, time.time() - self.opt.idle_s,
                                               "+inf")))

    @contextlib.contextmanager
    def locked(self, robot_id: str, strict_map: bool = True) -> Iterator[Session]:
        token = secrets.token_hex(8)
        lock_key, key = self._k_lock + robot_id, self._k_session + robot_id
        with self._local_lock(robot_id):  # threads of this replica queue here
            res = self._acquire(robot_id, token, lock_key, key)
            saved = False
            try:
                s = self._materialize(robot_id, res[1:], strict_map)
                if s is None:
                    raise NotFound(f"no session for robot '{robot_id}'")
                loaded = s.version
                yield s
                version = secrets.token_hex(8)
                blob = encode_stored(s)
                with self._io():
                    ok = self._save_release(
                        keys=[lock_key, key, self._index],
                        args=[token, loaded or "", version, blob, s.localizer.map.name,
                              self._ttl_ms(), time.time(), robot_id])
                saved = True
                if not ok:
                    raise Conflict(f"the session of robot '{robot_id}' changed meanwhile "
                                   "(replaced, deleted, or this replica's lock lease ran out "
                                   "and another frame went first); this frame was not applied")
                s.version = version
            except BaseException:
                self._cache.pop(robot_id, None)  # possibly half-changed: reload next time
                if not saved:
                    with contextlib.suppress(*self._errors):
                        self._release(keys=[lock_key], args=[token])
                raise

    def _acquire(self, robot_id: str, token: str, lock_key: str, key: str) -> list[Any]:
        deadline = time.monotonic() + self.opt.lock_wait_s
        pause = 0.001
        lease_ms = max(1, round(self.opt.lock_lease_s * 1000))
        while True:
            cached = self._cache.get(robot_id)
            with self._io():
                res = self._acquire_load(keys=[lock_key, key], args=[
                    token, lease_ms, cached.version if cached and cached.version else ""])
            if res[0] == 1:
                return res
            if time.monotonic() >= deadline:
                raise Conflict(f"the session of robot '{robot_id}' is busy with another frame "
                               f"(on another replica) for over {self.opt.lock_wait_s:g} s; "
                               "send frames one at a time")
            time.sleep(pause)
            pause = min(pause * 2, 0.02)

    def expire(self, idle_s: float, now: float) -> list[str]:
        with self._io():
            raw = cast(list[bytes], self.r.zrangebyscore(self._index, "-inf", now - idle_s))
            gone = []
            for b in raw:  # the keys themselves expired with their TTL
                rid = b.decode()
                if not self.r.exists(self._k_session + rid):
                    self.r.zrem(self._index, rid)
                    gone.append(rid)
        for rid in gone:
            self._forget(rid)
        return gone

    def claim(self, robot_id: str) -> bool:
        with self._io():
            return bool(self._claim(keys=[self._k_claim + robot_id], args=[
                self.replica_id, max(1, round(self.opt.claim_lease_s * 1000))]))

    def close(self) -> None:
        self.r.close()
