"""Work that may wait for the service, off Zenoh's callback threads.

zenoh-python 1.x calls each declaration's Python callback on one thread of its own, fed by a
bounded queue: a callback that waits (a learning robot's delete or reset waits for its
learner, a map query for the map admin through a whole map write) holds every later message
of that declaration, and once that queue is full, Zenoh's receiving thread blocks on it: no
frame of any robot on that link arrives until the wait is over. So such a callback only hands
its work to a ``KeyedWorkers`` and returns.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

from service.api.errors import ServiceError

log = logging.getLogger("swarmloc.zenoh")


@dataclass
class _Job:
    run: Callable[[], None]
    refuse: Callable[[ServiceError], None]


class KeyedWorkers:
    """A few threads of their own running jobs, a key's (a robot's, a map's) one at a time in
    the order they came. At most ``per_key`` jobs wait per key and at most ``max_keys`` keys
    have jobs waiting; beyond, a job is refused at once (``refuse`` with a 503, and ``busy``
    called). At ``close`` the jobs not started are refused with a 503."""

    def __init__(self, name: str, workers: int, per_key: int, max_keys: int, what: str,
                 busy: Callable[[], None] | None = None) -> None:
        self.per_key = per_key
        self.max_keys = max_keys
        self.what = what  # "control queries": for the refusal's message
        self._busy = busy or (lambda: None)
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix=name)
        self._lock = threading.Lock()
        # a key's jobs wait in order in its queue, which exists while a worker drains it
        self._queues: dict[str, deque[_Job]] = {}
        self._closed = False

    def submit(self, key: str, run: Callable[[], None],
               refuse: Callable[[ServiceError], None]) -> None:
        """Queue ``run`` after the key's earlier jobs and return; ``refuse`` answers it
        instead where too many wait or the service is shutting down."""
        job = _Job(run, refuse)
        start = False
        with self._lock:
            closed = self._closed
            waiting = self._queues.get(key)
            refused = not closed and (len(self._queues) >= self.max_keys if waiting is None
                                      else len(waiting) >= self.per_key)
            if not (closed or refused):
                start = waiting is None
                self._queues.setdefault(key, deque()).append(job)
        if refused:
            self._busy()
            self._refuse(job, ServiceError(
                f"too many {self.what} waiting; retry when they are answered", 503))
            return
        if closed:
            self._refuse(job, ServiceError("the service is shutting down", 503))
            return
        if not start:
            return
        try:
            self._pool.submit(self._drain, key)
        except RuntimeError:  # shutting down: the pool takes no more work
            with self._lock:
                left = self._queues.pop(key, deque())
            for j in left:
                self._refuse(j, ServiceError("the service is shutting down", 503))

    def close(self) -> None:
        """Take no more jobs; the jobs not started are refused (503), those running finish."""
        with self._lock:
            self._closed = True
            left = [j for q in self._queues.values() for j in q]
            self._queues.clear()
        self._pool.shutdown(wait=False, cancel_futures=True)
        for job in left:
            self._refuse(job, ServiceError("the service is shutting down", 503))

    def _drain(self, key: str) -> None:
        while True:
            with self._lock:
                waiting = self._queues.get(key)
                if not waiting:
                    self._queues.pop(key, None)
                    return
                job = waiting.popleft()
            try:
                job.run()
            except Exception:  # never leave the key's later jobs waiting for good
                log.exception("a Zenoh job for %s failed", key)

    @staticmethod
    def _refuse(job: _Job, exc: ServiceError) -> None:
        try:
            job.refuse(exc)
        except Exception:
            log.exception("refusing a Zenoh job failed")
