"""The learner's threads (service/engine/learn_queue.py): each key's jobs run in the order
handed over, other keys' jobs are not held up behind them, ``drain`` waits for them, a full
queue holds the next job back, a failing job is logged and the others run, ``close`` runs
what is queued."""

from __future__ import annotations

import logging
import threading
import zlib

import pytest

from service.engine.learn_queue import LearnQueue


def _keys_on_two_threads(threads: int) -> tuple[str, str]:
    """Two robot ids that the queue gives to different threads."""
    first = "robot-0"
    for i in range(1, 100):
        other = f"robot-{i}"
        if zlib.crc32(other.encode()) % threads != zlib.crc32(first.encode()) % threads:
            return first, other
    raise AssertionError("no two keys on different threads")


def test_a_key_s_jobs_run_in_order_and_drain_waits_for_them() -> None:
    q = LearnQueue(threads=3)
    ran: list[int] = []
    gate = threading.Event()
    q.submit("r", lambda: gate.wait(60))
    for i in range(20):
        q.submit("r", lambda i=i: ran.append(i))
    assert not q.drain(timeout=0.05) and ran == []  # held up behind the first job
    gate.set()
    assert q.drain(timeout=60)
    assert ran == list(range(20))
    q.close()
    assert not q.running


def test_another_robot_s_jobs_are_not_held_up() -> None:
    q = LearnQueue(threads=2)
    a, b = _keys_on_two_threads(2)
    gate = threading.Event()
    ran = threading.Event()
    q.submit(a, lambda: gate.wait(60))
    q.submit(b, ran.set)
    assert ran.wait(60)  # while robot a's job still waits (one thread: it never would)
    gate.set()
    q.close()


def test_a_robot_s_drain_waits_for_its_own_jobs_only() -> None:
    """A robot's session end or reset (``drain(key=...)``) waits for its own frames, not for
    another robot's backlog; ``drain()`` still waits for every robot's."""
    q = LearnQueue(threads=2)
    a, b = _keys_on_two_threads(2)
    gate_a, gate_b = threading.Event(), threading.Event()
    ran_b: list[int] = []
    q.submit(a, lambda: gate_a.wait(60))
    assert q.drain(timeout=5, key=b)  # b handed nothing over: at once
    q.submit(b, lambda: gate_b.wait(60))
    q.submit(b, lambda: ran_b.append(1))
    assert not q.drain(timeout=0.05, key=b)  # b's own job holds it
    gate_b.set()
    assert q.drain(timeout=60, key=b) and ran_b == [1]  # while a's job still waits
    assert not q.drain(timeout=0.05) and not q.drain(timeout=0.05, key=a)
    q.submit(b, lambda: ran_b.append(2))  # b again, after its jobs had all run
    assert q.drain(timeout=60, key=b) and ran_b == [1, 2]
    gate_a.set()
    assert q.drain(timeout=60, key=a) and q.drain(timeout=60)
    q.close()


def test_a_full_queue_holds_the_next_job_back_until_a_place_frees() -> None:
    q = LearnQueue(maxsize=2, threads=1)
    gate = threading.Event()
    ran: list[int] = []
    q.submit("r", lambda: gate.wait(60))  # running: the two places below fill the queue
    q.submit("r", lambda: ran.append(1))
    q.submit("r", lambda: ran.append(2))
    third = threading.Thread(target=q.submit, args=("r", lambda: ran.append(3)))
    third.start()
    third.join(0.2)
    assert third.is_alive()  # waiting for a place, not dropped
    gate.set()
    third.join(60)
    assert not third.is_alive() and q.drain(60) and ran == [1, 2, 3]
    q.close()


def test_a_failing_job_is_logged_and_the_next_ones_run(caplog: pytest.LogCaptureFixture
                                                       ) -> None:
    q = LearnQueue()
    ran: list[int] = []

    def broken() -> None:
        raise ValueError("a damaged frame")

    with caplog.at_level(logging.ERROR, logger="swarmloc"):
        q.submit("r", broken)
        q.submit("r", lambda: ran.append(1))
        assert q.drain(60)
    assert ran == [1] and q.failed == 1
    assert "a damaged frame" in caplog.text and "goes on" in caplog.text
    q.close()


def test_close_runs_what_is_queued_and_later_jobs_run_at_once() -> None:
    q = LearnQueue()
    gate = threading.Event()
    ran: list[int] = []
    q.submit("r", lambda: gate.wait(60))
    q.submit("r", lambda: ran.append(1))
    threading.Timer(0.1, gate.set).start()
    q.close()
    assert ran == [1] and not q.running
    q.submit("r", lambda: ran.append(2))  # after close: here, now
    assert ran == [1, 2]


def test_close_waits_for_a_job_counted_before_it_and_handed_over_after() -> None:
    """A submit counts its job, then hands it over (it may wait for a place): a close in
    between runs that job too, so a drain after it does not wait forever. The submit is
    played by hand (counted, then put 0.3 s later, after the thread has stopped)."""
    q = LearnQueue(threads=1)
    ran: list[int] = []
    q.submit("r", lambda: ran.append(1))  # starts the thread
    assert q.drain(5)
    with q._cond:
        q._submitted += 1
        counts = q._keys.setdefault("r", [0, 0])
        counts[0] += 1
    late = threading.Timer(0.3, q._jobs[0].put, args=(("r", counts, lambda: ran.append(2)),))
    late.start()
    q.close()
    late.join()
    assert ran == [1, 2] and not q.running
    assert q.drain(1) and q.drain(1, key="r")


def test_the_learner_needs_a_thread() -> None:
    with pytest.raises(ValueError, match="at least one thread"):
        LearnQueue(threads=0)
