"""Sessions stored before service/ moved into sub-packages still restore: a snapshot and a
Redis state written by the code before the move (tests/data/premove-*.bin, which name classes
such as ``service.located_noise:LocatedNoise``) decode through the codec's alias table and
continue."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from client.lab.processes import RedisServer
from service.engine.state_codec import MOVED_MODULES, encode_session
from service.engine.store import InProcessStore, RedisOptions, RedisStore
from service.estimators.along_track import AlongTrackSmoother
from service.estimators.multi_swarm_dpso import MultiSwarmDPSO
from service.maps.route_map import RouteMap

DATA = Path(__file__).parent / "data"


def _any_version(m: RouteMap):
    # the states were saved against this test map as built on the machine that wrote them;
    # the checksum of a rebuild may differ (another OpenCV), so the version is not checked
    def resolve(name: str, checksum: str | None, strict: bool) -> RouteMap:
        assert name == m.name
        return m
    return resolve


def _steps_on(loc, sunny2) -> None:
    seq = loc.last.seq if loc.last is not None else 0
    est = loc.step(loc.extract(sunny2.load_image(6)), t=6.0)
    assert est.seq == seq + 1 and np.isfinite([est.x, est.y]).all()


def test_snapshot_from_before_the_move_restores(small_map: RouteMap, sunny2, tmp_path: Path
                                                ) -> None:
    snap = tmp_path / "sessions.snap"
    snap.write_bytes((DATA / "premove-snapshot.bin").read_bytes())
    store = InProcessStore()
    restored, problems = store.load_snapshot(snap, _any_version(small_map))
    assert (restored, problems) == (4, [])
    kinds = {rid: store.get(rid).localizer for rid in store.ids()}  # type: ignore[union-attr]
    assert isinstance(kinds["robot-0"].estimator, MultiSwarmDPSO)
    assert [loc.estimator_name for _, loc in sorted(kinds.items())] == \
        ["dpso", "dpso", "pf-g", "pf-l"]
    assert kinds["robot-1"].params.get("variant") == "paper"
    for loc in kinds.values():
        _steps_on(loc, sunny2)
    # stored again, it names the new modules only
    s = store.get("robot-0")
    assert s is not None
    blob = encode_session(s)
    assert b"service.estimators.along_track:AlongTrackSmoother" in blob
    assert not any(old.encode() + b":" in blob for old in MOVED_MODULES)


def test_redis_state_from_before_the_move_restores(redis_srv: RedisServer, rdb,
                                                   small_map: RouteMap, sunny2) -> None:
    blob = (DATA / "premove-redis-dpso.bin").read_bytes()
    assert b"service.along_track:AlongTrackSmoother" in blob  # written before the move
    rdb.hset("swarmloc:s:old-robot", mapping={"v": "1", "st": blob, "map": "small"})
    store = RedisStore(redis_srv.url, _any_version(small_map), RedisOptions())
    try:
        s = store.get("old-robot")
        assert s is not None and s.robot_id == "robot-0"
        assert isinstance(s.localizer.estimator, MultiSwarmDPSO)
        assert isinstance(s.localizer.estimator.smoother, AlongTrackSmoother)
        _steps_on(s.localizer, sunny2)
    finally:
        store.close()
