"""The map writes of learning sessions, off the frame path, and one writer per map.

A frame that fills a learning session's collection only hands the batch over (``submit``, a
queue append); one background thread per service writes the batches in the order they came,
so a batch handed over while a write is in progress waits and is written next. A failed
write is logged (with the map, the experience and its images) and the sessions go on.
``close`` at shutdown writes what is queued within its deadline and logs what it dropped.

With the Redis store the replicas may run on several machines that share one maps directory,
where the file lock of ``MapAdmin`` does not reach. Then exactly one replica writes a map at
a time (``RedisHandover``):

1. the batch is appended to the map's list in Redis, ``{prefix}:learn:{map}`` (RPUSH);
2. the replica takes the map's writer lease, ``{prefix}:writer:{map}`` (``SET NX PX`` with a
   random token; renewed while it writes). Not taken: the holder writes the batch;
3. the holder writes the batches from the head of the list, one by one, each onto the newest
   version on disk, and removes a batch only once it is written (a Lua script that removes it
   only while the lease is still its own), then releases the lease (compare-and-delete) and
   looks once more: a batch appended while it released is written by whoever takes the lease
   next, itself included.

A holder that dies leaves its lease to expire and its batch at the head of the list; every
replica looks at the lists of its maps every ``SWEEP_S`` and writes what it finds. A batch
written twice (a holder that died after the write, before the removal) adds nothing: an
experience keeps one image per place. The other replicas see the new version on disk at their
next ``GET /maps/{name}``, session start or reset (``MapAdmin.refresh``).
"""

from __future__ import annotations

import contextlib
import logging
import queue
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.engine.state_codec import StateError, dumps, loads
from service.engine.store import RELEASE_LEASE
from service.maps.experiences import NewImage

log = logging.getLogger("swarmloc")

LEASE_S = 10.0  # a dead writer's lease expires after this (renewed every third of it)
SWEEP_S = 5.0  # how often an idle writer looks for batches that a dead holder left


@dataclass(frozen=True)
class Batch:
    """A learning session's collected images for experience ``exp_id`` of map ``map``."""

    map: str
    exp_id: str
    images: list[NewImage]
    condition: str | None
    robot: str
    base: str | None = None  # ``base_identity`` of the map they were learned on (None: any)

    def describe(self) -> str:
        return f"map {self.map} experience {self.exp_id} ({len(self.images)} images)"

    def encode(self) -> bytes:
        return dumps({"map": self.map, "exp_id": self.exp_id, "condition": self.condition,
                      "robot": self.robot, "base": self.base,
                      "images": [{"codes": f.codes, "keypoints": f.keypoints,
                                  "xy": np.asarray(f.xy, float), "name": f.name,
                                  **({} if f.codes2 is None else
                                     {"codes2": f.codes2, "keypoints2": f.keypoints2})}
                                 for f in self.images]})

    @staticmethod
    def decode(blob: bytes) -> Batch:
        """A batch from ``encode`` (StateError: damaged or not one)."""
        d = loads(blob)
        try:
            images = [NewImage(i["codes"], i["keypoints"], i["xy"], str(i["name"]),
                               i.get("codes2"), i.get("keypoints2")) for i in d["images"]]
            return Batch(str(d["map"]), str(d["exp_id"]), images, d["condition"],
                         str(d["robot"]), d.get("base"))
        except (KeyError, TypeError) as exc:
            raise StateError(f"not a learned batch: {exc}") from None


Write = Callable[[Batch], None]  # writes one batch into its map (raises when it cannot)

_POP = """
if redis.call('GET', KEYS[1]) == ARGV[1] then
  redis.call('LPOP', KEYS[2])
  redis.call('PEXPIRE', KEYS[1], ARGV[2])
  return 1
end
return 0
"""
_RENEW = """
if redis.call('GET', KEYS[1]) == ARGV[1] then return redis.call('PEXPIRE', KEYS[1], ARGV[2]) end
return 0
"""


class RedisHandover:
    """The maps' learned batches in Redis and their writer leases (steps 1-3 above)."""

    def __init__(self, r: Any, prefix: str = "swarmloc", lease_s: float = LEASE_S) -> None:
        self.r = r
        self.prefix = prefix
        self.lease_ms = max(1, round(lease_s * 1000))
        self._pop = r.register_script(_POP)
        self._renew = r.register_script(_RENEW)
        self._release = r.register_script(RELEASE_LEASE)  # compare-and-delete

    def queue_key(self, name: str) -> str:
        return f"{self.prefix}:learn:{name}"

    def lease_key(self, name: str) -> str:
        return f"{self.prefix}:writer:{name}"

    def push(self, batch: Batch) -> None:
        self.r.rpush(self.queue_key(batch.map), batch.encode())

    def waiting(self, names: list[str]) -> dict[str, int]:
        """Batches waiting in Redis per map (maps with none left out)."""
        pipe = self.r.pipeline()
        for n in names:
            pipe.llen(self.queue_key(n))
        return {n: int(k) for n, k in zip(names, pipe.execute(), strict=True) if k}

    @contextlib.contextmanager
    def _renewing(self, key: str, token: str) -> Iterator[None]:
        stop = threading.Event()

        def renew() -> None:
            while not stop.wait(self.lease_ms / 3000):
                with contextlib.suppress(Exception):  # a lost lease shows at the removal
                    self._renew(keys=[key], args=[token, self.lease_ms])

        t = threading.Thread(target=renew, name="experience-lease", daemon=True)
        t.start()
        try:
            yield
        finally:
            stop.set()
            t.join()

    def drain(self, name: str, write: Write) -> int:
        """Write map ``name``'s waiting batches if this replica gets its writer lease; the
        number written (0: none waiting, or another replica holds the lease and writes)."""
        lease, key = self.lease_key(name), self.queue_key(name)
        written = 0
        while True:
            token = secrets.token_hex(8)
            if not self.r.set(lease, token, nx=True, px=self.lease_ms):
                return written  # the holder writes what is waiting
            try:
                with self._renewing(lease, token):
                    while (blob := self.r.lindex(key, 0)) is not None:
                        try:
                            batch: Batch | None = Batch.decode(blob)
                        except StateError as exc:
                            log.error("map %s: a damaged learned batch dropped: %s", name, exc)
                            batch = None
                        if batch is not None:
                            _write_logged(write, batch)
                            written += 1
                        if not self._pop(keys=[lease, key], args=[token, self.lease_ms]):
                            log.warning("map %s: writer lease lost during a write; the batch "
                                        "stays queued for the next writer", name)
                            return written
            finally:
                self._release(keys=[lease], args=[token])
            if not self.r.llen(key):  # appended while it released: take the lease again
                return written


def _write_logged(write: Write, batch: Batch) -> bool:
    try:
        write(batch)
    except Exception as exc:  # a map that cannot take it keeps serving as it is
        log.error("%s not written: %s: %s", batch.describe(), type(exc).__name__, exc)
        return False
    return True


class ExperienceWriter:
    """The background writer of one service (module docstring)."""

    def __init__(self, write: Write, handover: RedisHandover | None = None,
                 maps: Callable[[], list[str]] = list, sweep_s: float = SWEEP_S,
                 waiting: Callable[[int], None] | None = None) -> None:
        self._write = write
        self._waiting = waiting  # told the number of batches not done after each change
        self.handover = handover
        self._maps = maps
        self._sweep_s = sweep_s
        self._queue: queue.Queue[Batch | None] = queue.Queue()
        self._unpushed: deque[Batch] = deque()  # Redis: taken from the queue, not yet pushed
        self._busy: Batch | None = None  # the batch being written (no Redis)
        self._submitted = 0
        self._done = 0
        self._cond = threading.Condition()
        self._closed = False
        self._thread = threading.Thread(target=self._work, name="experience-writer",
                                        daemon=True)
        self._thread.start()

    def submit(self, map_name: str, exp_id: str, images: list[NewImage],
               condition: str | None, robot: str, base: str | None = None) -> None:
        """Hand a batch over (the frame path: a queue append, never a write); ``base``: the
        ``base_identity`` of the map the images were learned on."""
        batch = Batch(map_name, exp_id, images, condition, robot, base)
        with self._cond:
            if self._closed:
                log.warning("%s dropped: the service is shutting down", batch.describe())
                return
            self._submitted += 1
            self._report()
        self._queue.put(batch)

    def _report(self) -> None:
        if self._waiting is not None:
            self._waiting(self._submitted - self._done)

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait until every batch handed over so far is written (or, with Redis, handed to
        the map's writer); True when it is."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cond:
            while self._done < self._submitted:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return False
                self._cond.wait(left)
        return True

    def close(self, timeout_s: float) -> list[str]:
        """At shutdown: write what is queued within ``timeout_s``; the batches dropped
        (logged) are returned, described."""
        with self._cond:
            self._closed = True
        self._queue.put(None)
        self._thread.join(timeout_s)
        dropped: list[Batch] = []
        if self._thread.is_alive():
            with self._cond:
                dropped = [*([self._busy] if self._busy else []), *self._unpushed]
            while True:
                try:
                    b = self._queue.get_nowait()
                except queue.Empty:
                    break
                if b is not None:
                    dropped.append(b)
            self._queue.put(None)  # the worker still ends once its write returns
        for b in dropped:
            log.warning("shutdown after %.1f s: %s dropped", timeout_s, b.describe())
        return [b.describe() for b in dropped]

    # ---- the worker --------------------------------------------------------------------
    def _finished(self, n: int = 1) -> None:
        with self._cond:
            self._done += n
            self._busy = None
            self._report()
            self._cond.notify_all()

    def _work(self) -> None:
        while True:
            timeout = None if self.handover is None else (1.0 if self._unpushed
                                                          else self._sweep_s)
            try:
                b = self._queue.get(timeout=timeout)
            except queue.Empty:  # Redis only: retry a failed hand-over, or look for leftovers
                if self._unpushed:
                    self._hand_over()
                else:
                    self._sweep()
                continue
            if b is None:  # closed: everything submitted came before this
                while self._unpushed:  # Redis down: retried until close's deadline
                    self._hand_over()
                    if self._unpushed:
                        time.sleep(0.2)
                return
            if self.handover is None:
                with self._cond:
                    self._busy = b
                _write_logged(self._write, b)
                self._finished()
            else:
                with self._cond:
                    self._unpushed.append(b)
                self._hand_over()

    def _hand_over(self) -> None:
        """Redis: push the batches in order, then write their maps' lists if the lease is
        free. A Redis error leaves the rest, in order, for the next try (nothing dropped)."""
        assert self.handover is not None
        maps: list[str] = []
        pushed = 0
        try:
            while self._unpushed:
                b = self._unpushed[0]
                self.handover.push(b)
                with self._cond:
                    self._unpushed.popleft()
                pushed += 1
                if b.map not in maps:
                    maps.append(b.map)
            for name in maps:
                self.handover.drain(name, self._write)
        except Exception as exc:
            log.warning("learned batches not handed over yet (%d waiting): %s: %s",
                        len(self._unpushed), type(exc).__name__, exc)
        finally:
            if pushed:
                self._finished(pushed)

    def _sweep(self) -> None:
        """Redis: write batches that a writer which died left in the lists."""
        assert self.handover is not None
        try:
            for name in self.handover.waiting(self._maps()):
                self.handover.drain(name, self._write)
        except Exception as exc:
            log.debug("learned batches in Redis not looked at: %s: %s",
                      type(exc).__name__, exc)
