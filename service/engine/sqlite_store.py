"""``SqliteStore``: the durable single-machine session store (the default).

One SQLite file in WAL mode, one row per robot ``(robot_id, version, map, last_used, state)``
with the state blob of service/engine/state_codec.py. The live Session objects stay cached in
the process, so a frame costs one encode and one UPDATE (no decode); a row is decoded only on
a cache miss (after a restart, or after a frame failed and its half-changed object was
dropped). Every write is a compare-and-set on ``version`` (a counter unique within the file),
so a frame still running on a session that was replaced or deleted meanwhile is refused (409),
never written over the newer row.

Durability: a commit in WAL mode with ``synchronous=NORMAL`` has been written to the WAL file
(the OS page cache) when it returns, so a crash of the process (kill -9, OOM killer, segfault)
loses no applied frame; only an OS crash or a power cut can undo the last commits, and the
file stays consistent either way. ``?synchronous=full`` fsyncs every commit as well (durable
against power loss too, at the cost of one fsync per frame).

The file is opened with ``locking_mode=EXCLUSIVE``: one process at a time (a second
``swarmloc serve`` on the same file is refused at start-up with the reason); replicas that
share sessions use Redis. A file that is not a SQLite database, or a SQLite database that is
not a swarmloc session store, is refused at start-up and left untouched.
"""

from __future__ import annotations

import contextlib
import sqlite3
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Literal, cast
from urllib.parse import parse_qs, urlsplit

from service.api.errors import Conflict, NotFound, Unavailable
from service.engine.store import (
    MapResolver,
    Session,
    SessionLimit,
    SessionStore,
    decode_stored,
    encode_stored,
    robot_lock,
)

APPLICATION_ID = 0x53574C53  # b"SWLS": PRAGMA application_id of a swarmloc session store
SCHEMA_VERSION = 1  # PRAGMA user_version
DEFAULT_FILE = "sessions.sqlite"  # in the maps directory (writable: maps are uploaded there)
Synchronous = Literal["NORMAL", "FULL"]

_SCHEMA = """
CREATE TABLE sessions (
    robot_id TEXT PRIMARY KEY,
    version INTEGER NOT NULL,
    map TEXT NOT NULL,
    last_used REAL NOT NULL,
    state BLOB NOT NULL
) WITHOUT ROWID
"""


class SessionStoreError(RuntimeError):
    """The session store cannot be opened (start-up): the message says why and what to do."""


def sqlite_location(url: str, maps_dir: Path) -> tuple[Path, Synchronous]:
    """The file and the synchronous mode of ``SWARMLOC_SESSION_STORE``: ``sqlite`` (the file
    ``sessions.sqlite`` in the maps directory) or ``sqlite:///PATH`` (relative) /
    ``sqlite:////ABS/PATH``, optionally with ``?synchronous=full``."""
    if url == "sqlite":
        return Path(maps_dir) / DEFAULT_FILE, "NORMAL"
    parts = urlsplit(url)
    if parts.scheme != "sqlite" or parts.netloc or not parts.path.startswith("/") \
            or len(parts.path) < 2:
        raise ValueError(f"SWARMLOC_SESSION_STORE={url!r}: use 'sqlite', sqlite:///relative/"
                         "path or sqlite:////absolute/path")
    query = parse_qs(parts.query)
    unknown = set(query) - {"synchronous"}
    sync = query.get("synchronous", ["normal"])[-1].upper()
    if unknown or sync not in ("NORMAL", "FULL"):
        raise ValueError(f"SWARMLOC_SESSION_STORE={url!r}: the only option is "
                         "?synchronous=normal (default) or ?synchronous=full")
    return Path(parts.path[1:]), cast(Synchronous, sync)


def sqlite_url(path: Path) -> str:
    """``SWARMLOC_SESSION_STORE`` for the SQLite file ``path``."""
    return f"sqlite:///{Path(path).absolute()}"


def _open(path: Path, synchronous: Synchronous, busy_s: float) -> sqlite3.Connection:
    """The connection, holding the file's exclusive lock; SessionStoreError with the reason."""
    advice = ("set SWARMLOC_SESSION_STORE to another file (sqlite:////path/sessions.sqlite) "
              "or to 'memory'")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        db = sqlite3.connect(path, timeout=busy_s, isolation_level=None,
                             check_same_thread=False)
    except (OSError, sqlite3.Error) as exc:
        raise SessionStoreError(f"cannot open the session store {path}: {exc}; {advice}"
                                ) from None
    try:
        db.execute("PRAGMA locking_mode=EXCLUSIVE")  # before WAL: no shared-memory index
        db.execute("BEGIN IMMEDIATE")  # the lock, held until close (exclusive mode)
        tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master")}
        app = db.execute("PRAGMA application_id").fetchone()[0]
        if not tables and app == 0:  # a new file
            db.execute(_SCHEMA)
            db.execute(f"PRAGMA application_id={APPLICATION_ID}")
            db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
        elif app != APPLICATION_ID:
            raise SessionStoreError(f"{path} is a SQLite database of something else (tables: "
                                    f"{', '.join(sorted(tables)) or 'none'}), not a swarmloc "
                                    f"session store; left untouched; {advice}")
        elif (v := db.execute("PRAGMA user_version").fetchone()[0]) != SCHEMA_VERSION:
            raise SessionStoreError(f"{path} is a swarmloc session store of format {v}; this "
                                    f"version reads format {SCHEMA_VERSION}; {advice}")
        db.execute("COMMIT")
        mode = db.execute("PRAGMA journal_mode=WAL").fetchone()[0]
        if str(mode).lower() != "wal":
            raise SessionStoreError(f"{path}: SQLite refused WAL mode (got {mode}); {advice}")
        db.execute(f"PRAGMA synchronous={synchronous}")
        check = [r[0] for r in db.execute("PRAGMA quick_check")]
        if check != ["ok"]:
            raise SessionStoreError(f"{path} is damaged (SQLite quick_check: "
                                    f"{'; '.join(map(str, check[:3]))}); left untouched; move "
                                    f"it aside or {advice}")
    except SessionStoreError:
        db.close()
        raise
    except sqlite3.Error as exc:
        db.close()
        if "locked" in str(exc) or "busy" in str(exc):
            raise SessionStoreError(f"the session store {path} is in use by another process "
                                    f"(another swarmloc serve?); {advice}, or use Redis to "
                                    "share sessions between replicas") from None
        raise SessionStoreError(f"{path} is not a readable swarmloc session store "
                                f"({type(exc).__name__}: {exc}); left untouched; move it "
                                f"aside or {advice}") from None
    return db


class SqliteStore(SessionStore):
    def __init__(self, path: Path, resolve: MapResolver, synchronous: Synchronous = "NORMAL",
                 busy_s: float = 2.0) -> None:
        self.path = Path(path)
        self.synchronous = synchronous
        self._resolve = resolve
        self._db = _open(self.path, synchronous, busy_s)
        self._io_lock = threading.Lock()  # the connection, the cache and the version counter
        self._cache: dict[str, Session] = {}  # the live sessions (equal to their rows)
        self._local: dict[str, threading.Lock] = {}  # one per robot: its frames queue here
        self._guard = threading.Lock()
        with self._io():
            self._version = int(self._db.execute(
                "SELECT COALESCE(MAX(version), 0) FROM sessions").fetchone()[0])

    # ---- helpers ----------------------------------------------------------------------
    @contextlib.contextmanager
    def _io(self) -> Iterator[sqlite3.Connection]:
        """The connection, held exclusively; a SQLite error (disk full, I/O) is a 503."""
        with self._io_lock:
            try:
                yield self._db
            except sqlite3.Error as exc:
                raise Unavailable(f"session store unavailable (SQLite at {self.path}): "
                                  f"{type(exc).__name__}: {exc}; retry shortly") from None

    def _next_version(self) -> int:
        self._version += 1
        return self._version

    def _local_lock(self, robot_id: str) -> threading.Lock:
        return robot_lock(self._local, self._guard, robot_id)

    def _load(self, db: sqlite3.Connection, robot_id: str, strict: bool) -> Session | None:
        """The cached session, or its row decoded (cached when on the loaded map version);
        called with the connection held, so no write or delete slips in between."""
        cached = self._cache.get(robot_id)
        if cached is not None:
            return cached
        row = db.execute("SELECT version, state FROM sessions WHERE robot_id = ?",
                         (robot_id,)).fetchone()
        if row is None:
            return None
        s = decode_stored(robot_id, str(row[0]), row[1], self._resolve, strict)
        if not s.map_changed:
            self._cache[robot_id] = s
        return s

    def _save(self, s: Session) -> None:
        """Write the session back if its row is still the version it was loaded at."""
        blob = encode_stored(s)
        with self._io() as db:
            version = self._next_version()
            n = db.execute(
                "UPDATE sessions SET version = ?, map = ?, last_used = ?, state = ? "
                "WHERE robot_id = ? AND version = ?",
                (version, s.localizer.map.name, s.last_used, blob, s.robot_id,
                 int(s.version or 0))).rowcount
            if n != 1:
                raise Conflict(f"the session of robot '{s.robot_id}' was replaced or deleted "
                               "meanwhile; this frame was not applied")
            s.version = str(version)
            if not s.map_changed:
                self._cache[s.robot_id] = s

    def _drop(self, robot_id: str, s: Session) -> None:
        with self._io_lock:
            if self._cache.get(robot_id) is s:
                del self._cache[robot_id]

    # ---- the interface ----------------------------------------------------------------
    def get(self, robot_id: str) -> Session | None:
        with self._io() as db:
            return self._load(db, robot_id, strict=False)

    def create(self, session: Session, replace: bool, max_sessions: int
               ) -> tuple[Session, bool]:
        rid = session.robot_id
        blob = encode_stored(session)
        with self._io() as db:
            exists = db.execute("SELECT 1 FROM sessions WHERE robot_id = ?",
                                (rid,)).fetchone() is not None
            if exists and not replace:
                kept = self._load(db, rid, strict=False)
                assert kept is not None
                return kept, False
            if not exists and \
                    db.execute("SELECT COUNT(*) FROM sessions").fetchone()[0] >= max_sessions:
                raise SessionLimit
            version = self._next_version()
            db.execute("INSERT OR REPLACE INTO sessions (robot_id, version, map, last_used, "
                       "state) VALUES (?, ?, ?, ?, ?)",
                       (rid, version, session.localizer.map.name, session.last_used, blob))
            session.version = str(version)
            self._cache[rid] = session
        return session, not exists

    def delete(self, robot_id: str) -> bool:
        with self._io() as db:
            n = db.execute("DELETE FROM sessions WHERE robot_id = ?", (robot_id,)).rowcount
            self._cache.pop(robot_id, None)
        with self._guard:
            self._local.pop(robot_id, None)
        return n > 0

    def ids(self) -> list[str]:
        with self._io() as db:
            return [r[0] for r in db.execute("SELECT robot_id FROM sessions")]

    def maps_of(self) -> dict[str, str]:
        with self._io() as db:
            return dict(db.execute("SELECT robot_id, map FROM sessions").fetchall())

    def __len__(self) -> int:
        with self._io() as db:
            return int(db.execute("SELECT COUNT(*) FROM sessions").fetchone()[0])

    @contextlib.contextmanager
    def locked(self, robot_id: str, strict_map: bool = True) -> Iterator[Session]:
        with self._local_lock(robot_id):
            with self._io() as db:
                s = self._load(db, robot_id, strict_map)
            if s is None:
                raise NotFound(f"no session for robot '{robot_id}'")
            try:
                yield s
                self._save(s)
            except BaseException:
                self._drop(robot_id, s)  # possibly half-changed: its row is read next time
                raise

    def expire(self, idle_s: float, now: float) -> list[str]:
        with self._io() as db:
            idle = [r[0] for r in db.execute(
                "SELECT robot_id FROM sessions WHERE last_used < ?", (now - idle_s,))]
            with self._guard:
                gone = [rid for rid in idle
                        if not (rid in self._local and self._local[rid].locked())]
                for rid in gone:
                    self._local.pop(rid, None)
            db.executemany("DELETE FROM sessions WHERE robot_id = ?", [(r,) for r in gone])
            for rid in gone:
                self._cache.pop(rid, None)
        return gone

    def close(self) -> None:
        with self._io_lock:
            with contextlib.suppress(sqlite3.Error):
                self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
            self._db.close()
