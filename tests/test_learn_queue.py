"""The learner's thread (service/engine/learn_queue.py): jobs run in the order handed over,
``drain`` waits for them, a full queue holds the next one back, a failing job is logged and
the others run, ``close`` runs what is queued."""

from __future__ import annotations

import logging
import threading

import pytest

from service.engine.learn_queue import LearnQueue


def test_jobs_run_in_order_on_one_thread_and_drain_waits_for_them() -> None:
    q = LearnQueue()
    ran: list[tuple[int, str]] = []
    gate = threading.Event()
    q.submit(lambda: gate.wait(60))
    for i in range(20):
        q.submit(lambda i=i: ran.append((i, threading.current_thread().name)))
    assert not q.drain(timeout=0.05) and ran == []  # held up behind the first job
    gate.set()
    assert q.drain(timeout=60)
    assert [i for i, _ in ran] == list(range(20))
    assert {name for _, name in ran} == {"swarmloc-learn"}
    q.close()
    assert not q.running


def test_a_full_queue_holds_the_next_job_back_until_a_place_frees() -> None:
    q = LearnQueue(maxsize=2)
    gate = threading.Event()
    ran: list[int] = []
    q.submit(lambda: gate.wait(60))  # running: the two places below fill the queue
    q.submit(lambda: ran.append(1))
    q.submit(lambda: ran.append(2))
    third = threading.Thread(target=q.submit, args=(lambda: ran.append(3),))
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
        q.submit(broken)
        q.submit(lambda: ran.append(1))
        assert q.drain(60)
    assert ran == [1] and q.failed == 1
    assert "a damaged frame" in caplog.text and "goes on" in caplog.text
    q.close()


def test_close_runs_what_is_queued_and_later_jobs_run_at_once() -> None:
    q = LearnQueue()
    gate = threading.Event()
    ran: list[int] = []
    q.submit(lambda: gate.wait(60))
    q.submit(lambda: ran.append(1))
    threading.Timer(0.1, gate.set).start()
    q.close()
    assert ran == [1] and not q.running
    q.submit(lambda: ran.append(2))  # after close: here, now
    assert ran == [1, 2]
