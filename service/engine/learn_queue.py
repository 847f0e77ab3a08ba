"""The learning sessions' gates, off the frame path.

A learning robot's frame is answered as soon as it is localized: the learner's gates
(service/engine/learning.py; its two-view geometry, and at the frame that closes a stretch
bridged by the wheels the appearance check of every held frame) run on one background thread
per service, in the order the frames were handed over (``submit``), so that a robot's
collection is the one the gates make frame by frame. The queue is bounded
(``LEARN_QUEUE_FRAMES``): where the thread falls behind, the next learning frame waits for a
place, so the learner never drops a frame, and only learning robots wait. ``drain`` waits for
what was handed over before it (a session's end or reset, the statistics); ``close`` drains
and stops the thread (a job handed over after it runs at once). A job that fails is logged,
and the next one runs.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable

log = logging.getLogger("swarmloc")

LEARN_QUEUE_FRAMES = 64  # learning frames waiting for their gates (~115 kB of features each)


class LearnQueue:
    """One background thread that runs jobs in the order they were handed over."""

    def __init__(self, maxsize: int = LEARN_QUEUE_FRAMES) -> None:
        self._jobs: queue.Queue[Callable[[], None] | None] = queue.Queue(maxsize)
        self._cond = threading.Condition()
        self._submitted = 0
        self._done = 0
        self._thread: threading.Thread | None = None
        self._closed = False
        self.failed = 0  # jobs that raised

    def submit(self, job: Callable[[], None]) -> None:
        """Hand ``job`` to the thread (started on the first job); waits for a place where the
        queue is full; runs it here once the queue is closed."""
        with self._cond:
            closed = self._closed
            if not closed:
                if self._thread is None:
                    self._thread = threading.Thread(target=self._run, name="swarmloc-learn",
                                                    daemon=True)
                    self._thread.start()
                self._submitted += 1
        if closed:
            self._call(job)
        else:
            self._jobs.put(job)

    def drain(self, timeout: float | None = None) -> bool:
        """Wait until every job handed over before this call has run (at once on the thread
        itself); False where ``timeout`` passed first."""
        if threading.current_thread() is self._thread:
            return True
        with self._cond:
            target = self._submitted
            return self._cond.wait_for(lambda: self._done >= target, timeout)

    def close(self) -> None:
        """Run what is queued and stop the thread."""
        with self._cond:
            thread, self._closed = self._thread, True
        if thread is not None and thread.is_alive():
            self._jobs.put(None)
            thread.join()
        while True:  # handed over while it closed: run here
            try:
                job = self._jobs.get_nowait()
            except queue.Empty:
                return
            if job is not None:
                self._call(job)
                with self._cond:
                    self._done += 1
                    self._cond.notify_all()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _call(self, job: Callable[[], None]) -> None:
        try:
            job()
        except Exception:  # a learning frame's failure must not stop the others
            self.failed += 1
            log.exception("learning: a frame's gates failed; the session goes on")

    def _run(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            self._call(job)
            with self._cond:
                self._done += 1
                self._cond.notify_all()
