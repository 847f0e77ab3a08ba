"""The learning sessions' gates, off the frame path.

A learning robot's frame is answered as soon as it is localized: the learner's gates
(service/engine/learning.py; its two-view geometry, and at the frame that closes a stretch
bridged by the wheels the appearance check of every held frame) run on the learner's own
threads. Each robot's frames go to one of them (``submit`` with the robot's id as the key),
in the order they were handed over, so that its collection is the one the gates make frame
by frame; several robots spread over ``LEARN_THREADS`` threads. Each thread's queue is
bounded (``LEARN_QUEUE_FRAMES``): where a thread falls behind, the next learning frame waits
for a place, so the learner never drops a frame, and only learning robots wait. ``drain``
waits for what was handed over before it: a robot's own frames for its session's end, reset
or statistics (``key``: another robot's backlog does not hold them), every robot's otherwise;
``close`` drains and stops the threads (a job handed over after it runs at once). A job that
fails is logged, and the next one runs.
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import zlib
from collections.abc import Callable

log = logging.getLogger("swarmloc")

LEARN_QUEUE_FRAMES = 64  # learning frames waiting for their gates, per thread (~115 kB each)
LEARN_THREADS = max(1, min(4, os.cpu_count() or 1))  # threads running the gates

Job = Callable[[], None]
_Item = tuple[str, list[int], Job]  # (key, the key's counts [handed over, run], the job)


class LearnQueue:
    """Background threads that run each key's jobs in the order they were handed over."""

    def __init__(self, maxsize: int = LEARN_QUEUE_FRAMES, threads: int = LEARN_THREADS
                 ) -> None:
        if threads < 1:
            raise ValueError(f"the learner needs at least one thread, got {threads}")
        self._jobs: list[queue.Queue[_Item | None]] = [queue.Queue(maxsize)
                                                       for _ in range(threads)]
        self._threads: list[threading.Thread | None] = [None] * threads
        self._cond = threading.Condition()
        self._submitted = 0
        self._done = 0
        # per key with jobs not yet run: [handed over, run] (a drained key's entry goes; a
        # drain holds its own entry's list, so a key handed jobs again starts a new one)
        self._keys: dict[str, list[int]] = {}
        self._closed = False
        self.failed = 0  # jobs that raised

    def submit(self, key: str, job: Job) -> None:
        """Hand ``job`` to ``key``'s thread (started on its first job), after the key's
        earlier jobs; waits for a place where its queue is full; runs it here once the queue
        is closed."""
        k = zlib.crc32(key.encode()) % len(self._jobs)
        with self._cond:
            closed = self._closed
            if not closed:
                if self._threads[k] is None:
                    t = threading.Thread(target=self._run, args=(self._jobs[k],),
                                         name=f"swarmloc-learn-{k}", daemon=True)
                    self._threads[k] = t
                    t.start()
                self._submitted += 1
                counts = self._keys.setdefault(key, [0, 0])
                counts[0] += 1
        if closed:
            self._call(job)
        else:
            self._jobs[k].put((key, counts, job))

    def drain(self, timeout: float | None = None, key: str | None = None) -> bool:
        """Wait until every job handed over before this call has run, or only ``key``'s (at
        once on one of the threads: a job may drain); False where ``timeout`` passed
        first."""
        if threading.current_thread() in self._threads:
            return True
        with self._cond:
            if key is None:
                target = self._submitted
                return self._cond.wait_for(lambda: self._done >= target, timeout)
            counts = self._keys.get(key)
            if counts is None:
                return True
            handed = counts[0]
            return self._cond.wait_for(lambda: counts[1] >= handed, timeout)

    def close(self) -> None:
        """Run what is queued and stop the threads."""
        with self._cond:
            self._closed = True
            threads = list(self._threads)
        for q, t in zip(self._jobs, threads, strict=True):
            if t is not None and t.is_alive():
                q.put(None)
                t.join()
        # handed over while it closed (a job counted before it may still be on its way): run
        # here, until every job counted has run
        while True:
            with self._cond:
                if self._done >= self._submitted:
                    return
            for q in self._jobs:
                try:
                    item = q.get(timeout=0.01)
                except queue.Empty:
                    continue
                if item is not None:
                    self._call(item[2])
                    self._ran(item[0], item[1])

    @property
    def running(self) -> bool:
        return any(t is not None and t.is_alive() for t in self._threads)

    def _call(self, job: Job) -> None:
        try:
            job()
        except Exception:  # a learning frame's failure must not stop the others
            with self._cond:
                self.failed += 1
            log.exception("learning: a frame's gates failed; the session goes on")

    def _ran(self, key: str, counts: list[int]) -> None:
        with self._cond:
            self._done += 1
            counts[1] += 1
            if counts[1] >= counts[0] and self._keys.get(key) is counts:  # all of key's ran
                del self._keys[key]
            self._cond.notify_all()

    def _run(self, jobs: queue.Queue[_Item | None]) -> None:
        while True:
            item = jobs.get()
            if item is None:
                return
            self._call(item[2])
            self._ran(item[0], item[1])
