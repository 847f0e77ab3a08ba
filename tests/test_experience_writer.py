"""The learned batches' background writer (service/engine/experience_writer.py): off the frame
path, in order, failures logged, shutdown flushes or says what it dropped; with Redis one
writer per map across replicas that share no file lock."""

from __future__ import annotations

import logging
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from service.engine.experience_writer import Batch, ExperienceWriter, RedisHandover
from service.engine.learning import _Trail
from service.engine.localization_service import LocalizationService
from service.engine.map_admin import MapAdmin
from service.maps.experiences import NewImage
from service.maps.route_map import RouteMap
from service.settings import Settings


def _images(n: int, at: float = 0.0) -> list[NewImage]:
    rng = np.random.default_rng(int(at))
    return [NewImage(rng.integers(0, 255, (4, 32), dtype=np.uint8),
                     rng.random((4, 2)).astype(np.float32), np.array([at + i, 0.0]), f"x/{i}")
            for i in range(n)]


class Recorder:
    """A write function: records the batches; ``gate`` (set) lets writes go ahead; ``fail``
    names experiences whose write raises; counts writes running at once."""

    def __init__(self, fail: tuple[str, ...] = ()) -> None:
        self.written: list[tuple[str, str]] = []
        self.gate = threading.Event()
        self.gate.set()
        self.fail = fail
        self.running = 0
        self.most_at_once = 0
        self._lock = threading.Lock()

    def __call__(self, b: Batch) -> None:
        with self._lock:
            self.running += 1
            self.most_at_once = max(self.most_at_once, self.running)
        try:
            self.gate.wait(10)
            time.sleep(0.005)  # a write takes a while: overlapping writers would show
            if b.exp_id in self.fail:
                raise OSError("disk full")
            with self._lock:
                self.written.append((b.robot, b.exp_id))
        finally:
            with self._lock:
                self.running -= 1


def test_a_full_collection_is_handed_over_not_written_in_the_frame(
        small_map: RouteMap, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Regression: the frame that filled a batch wrote the map version itself. Now it only
    hands the batch over; a batch handed over during a write is written next, in order."""
    started, release = threading.Event(), threading.Event()
    order: list[str] = []

    def slow_commit(self: MapAdmin, name: str, exp_id: str, images: list[NewImage],
                    condition: str | None, robot: str, base: str | None = None) -> None:
        started.set()
        release.wait(5)
        order.append(exp_id)

    monkeypatch.setattr(MapAdmin, "commit_experience", slow_commit)
    assert small_map.path is not None
    shutil.copy(small_map.path, tmp_path / "small.swmap")
    service = LocalizationService(Settings(maps_dir=tmp_path, session_store="memory"))
    learner = service.learner
    for robot, exp in (("r1", "e1"), ("r2", "e2")):
        learner._trails[robot] = _Trail(exp, "small", "cloudy", pending=_images(3),
                                        seqs=[1, 2, 3], odometry=[None] * 3,
                                        known=[True] * 3)
    learner.flush("r1")  # what observe() does when a collection is full
    assert started.wait(10) and not release.is_set()
    learner.flush("r2")  # while the first write is in progress: queued
    assert order == []  # neither flush waited for a write
    release.set()
    assert service.writer.wait(10)
    assert order == ["e1", "e2"]
    service.close()


def test_a_failed_write_is_logged_and_the_next_one_written(
        caplog: pytest.LogCaptureFixture) -> None:
    rec = Recorder(fail=("bad",))
    rec.gate.clear()
    waiting: list[int] = []  # what the gauge swarmloc_learned_batches_waiting is told
    w = ExperienceWriter(rec, waiting=waiting.append)
    with caplog.at_level(logging.ERROR, "swarmloc"):
        w.submit("m", "bad", _images(2), None, "r1")
        w.submit("m", "good", _images(2), None, "r1")
        assert waiting[:2] == [1, 2]
        rec.gate.set()
        assert w.wait(10)
    assert rec.written == [("r1", "good")]
    assert waiting[-1] == 0  # a failed batch is done too (logged), not waiting forever
    assert "map m experience bad (2 images) not written: OSError: disk full" in caplog.text
    assert w.close(5) == []


def test_shutdown_writes_the_queue_or_says_what_it_dropped(
        caplog: pytest.LogCaptureFixture) -> None:
    rec = Recorder()
    w = ExperienceWriter(rec)
    for k in range(3):
        w.submit("m", f"e{k}", _images(1), None, "r")
    assert w.close(10) == []  # within the deadline: everything written
    assert [e for _, e in rec.written] == ["e0", "e1", "e2"]
    w.submit("m", "late", _images(1), None, "r")  # after close: refused, said
    assert rec.written[-1][1] == "e2"

    stuck = Recorder()
    stuck.gate.clear()  # a write that does not finish before the deadline
    w = ExperienceWriter(stuck)
    for k in range(3):
        w.submit("m", f"e{k}", _images(2), None, "r")
    with caplog.at_level(logging.WARNING, "swarmloc"):
        dropped = w.close(0.3)
    assert dropped == [f"map m experience e{k} (2 images)" for k in range(3)]
    assert "dropped" in caplog.text and "experience e2" in caplog.text
    stuck.gate.set()


def test_a_batch_survives_the_trip_through_redis() -> None:
    b = Batch("m", "e1", _images(3, at=5.0), "dusk", "r9")
    back = Batch.decode(b.encode())
    assert (back.map, back.exp_id, back.condition, back.robot) == ("m", "e1", "dusk", "r9")
    for x, y in zip(back.images, b.images, strict=True):
        assert np.array_equal(x.codes, y.codes) and np.array_equal(x.keypoints, y.keypoints)
        assert np.array_equal(x.xy, y.xy) and x.name == y.name


def test_one_writer_per_map_across_replicas_without_a_shared_lock(rdb) -> None:
    """Two replicas (no file lock between them: other machines) learn on one map at once:
    the writes never overlap, none is lost or written twice, each robot's in order."""
    rec = Recorder()
    writers = [ExperienceWriter(rec, RedisHandover(rdb), lambda: ["m"]) for _ in range(2)]
    go = threading.Barrier(2)

    def teach(k: int) -> None:
        go.wait()
        for j in range(6):
            writers[k].submit("m", f"r{k}-{j}", _images(2), None, f"r{k}")

    threads = [threading.Thread(target=teach, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for w in writers:
        assert w.wait(30)
    assert rec.most_at_once == 1  # one writer at a time
    assert sorted(rec.written) == sorted((f"r{k}", f"r{k}-{j}") for k in range(2)
                                         for j in range(6))  # each once, none lost
    for k in range(2):
        assert [e for r, e in rec.written if r == f"r{k}"] == [f"r{k}-{j}" for j in range(6)]
    assert rdb.llen("swarmloc:learn:m") == 0 and rdb.get("swarmloc:writer:m") is None
    for w in writers:
        assert w.close(5) == []


def test_batches_a_dead_writer_left_are_written_after_its_lease(rdb) -> None:
    """A replica that died holding the lease, with a batch in the list: the lease expires and
    another replica's sweep writes the batch."""
    handover = RedisHandover(rdb)
    handover.push(Batch("m", "orphan", _images(2), None, "r0"))
    rdb.set("swarmloc:writer:m", "dead-replica", px=600)
    rec = Recorder()
    w = ExperienceWriter(rec, RedisHandover(rdb), lambda: ["m"], sweep_s=0.2)
    deadline = time.monotonic() + 20
    while not rec.written and time.monotonic() < deadline:
        time.sleep(0.05)
    assert rec.written == [("r0", "orphan")]
    assert rdb.llen("swarmloc:learn:m") == 0
    assert w.close(5) == []
