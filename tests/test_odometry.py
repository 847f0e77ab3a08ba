"""Wheel odometry (issue 33): the step between frames, its validation on HTTP, the fusion in
the estimators (a kidnap is still recovered) and the session state that carries it."""

from __future__ import annotations

import math
from functools import partial

import httpx
import numpy as np
import pytest

from client.dataset import Round, read_round
from client.lab.experiments import SimilarityTable, run
from client.lab.world import World
from client.runs import frames_to_recover, odometry_along
from service.api.errors import InvalidParameters
from service.api.models import Odometry, odometry
from service.api.round_format import DatasetError
from service.engine.localizer import Localizer
from service.engine.state_codec import SessionState, decode_session, encode_session
from service.estimators.odometry import LocatedGate, OdomHeading, OdomStep, body_step
from service.maps.route_map import RouteMap


def test_the_step_does_not_depend_on_the_odometry_origin() -> None:
    a, b = (1.0, 2.0, 0.3), (1.5, 2.4, 0.5)
    step = body_step(a, b, 0.0, 0.0)
    # the same two poses in another odometry frame (rotated by 1 rad, shifted)
    c, s = math.cos(1.0), math.sin(1.0)

    def moved(p: tuple[float, float, float]) -> tuple[float, float, float]:
        return (c * p[0] - s * p[1] + 7.0, s * p[0] + c * p[1] - 3.0, p[2] + 1.0)

    other = body_step(moved(a), moved(b), 0.0, 0.0)
    assert np.allclose([step.forward, step.left, step.turn],
                       [other.forward, other.left, other.turn])
    assert step.distance == pytest.approx(math.hypot(0.5, 0.4))


def test_the_heading_fit_finds_the_rotation_and_scale_between_odometry_and_map() -> None:
    h = OdomHeading()
    h.min_span_m = 1.0
    truth_offset, scale = 0.7, 1.03
    for k in range(30):  # a gentle curve, in odometry steps of 0.6 m
        h.advance(OdomStep(0.6, 0.0, 0.02, 0.0, 0.0))
        x, y, _ = h.pose
        c, s = math.cos(truth_offset), math.sin(truth_offset)
        h.observe(scale * np.array([c * x - s * y, s * x + c * y]) + [100.0, 50.0])
        assert k < 8 or h.offset is not None
    assert h.offset == pytest.approx(truth_offset, abs=1e-6)
    assert h.scale == pytest.approx(scale, abs=1e-6)
    d, _ = h.displacement(OdomStep(1.0, 0.0, 0.0, 0.0, 0.0), None)
    heading = truth_offset + h.pose[2]
    assert np.allclose(d, scale * np.array([math.cos(heading), math.sin(heading)]))


@pytest.mark.parametrize(("args", "message"), [
    ((1.0, 2.0, None), "missing odom_yaw"),
    ((None, None, None, 0.1), "variances need"),
    ((math.nan, 0.0, 0.0), "finite"),
    ((1e9, 0.0, 0.0), "less than or equal"),
    ((0.0, 0.0, 0.0, -1.0), "greater than or equal"),
])
def test_bad_odometry_is_refused_with_a_clear_message(args: tuple, message: str) -> None:
    with pytest.raises(InvalidParameters, match=message):
        odometry(*args)


def test_a_jump_in_odometry_is_refused_before_anything_changes(small_map: RouteMap,
                                                               sunny2: Round) -> None:
    loc = Localizer(small_map, "dpso", seed=1)
    f = [loc.extract(sunny2.load_image(i)) for i in range(3)]
    loc.step(f[0], 0.0, odom=Odometry(x=0.0, y=0.0, yaw=0.0))
    loc.step(f[1], 1.0, odom=Odometry(x=0.6, y=0.0, yaw=0.0))
    before = encode_session(SessionState("r", loc, 0.0, 0.0))
    with pytest.raises(InvalidParameters, match="more than 100 m"):
        loc.step(f[2], 2.0, odom=Odometry(x=500.0, y=0.0, yaw=0.0))
    assert encode_session(SessionState("r", loc, 0.0, 0.0)) == before


def test_an_odometry_session_survives_the_store_bit_for_bit(small_map: RouteMap,
                                                            sunny2: Round) -> None:
    assert sunny2.odometry is not None
    odom = [Odometry(x=float(x), y=float(y), yaw=float(a)) for x, y, a in sunny2.odometry]
    frames = [Localizer(small_map).extract(sunny2.load_image(i)) for i in range(40)]
    for est in ("dpso", "pf-l"):
        loc = Localizer(small_map, est, seed=2)
        for i in range(30):
            loc.step(frames[i], float(i), odom=odom[i])
        twin = decode_session(encode_session(SessionState("r", loc, 0.0, 0.0)),
                              lambda name, checksum: small_map).localizer
        odo = twin.estimator.odometry
        assert twin.odom_prev == loc.odom_prev and odo is not None and odo.offset is not None
        for i in range(30, 40):
            a = loc.step(frames[i], float(i), odom=odom[i])
            b = twin.step(frames[i], float(i), odom=odom[i])
            assert a == b


def test_the_kidnapped_robot_is_found_again_with_odometry(small_world: World,
                                                          small_map: RouteMap, sunny2: Round,
                                                          table: SimilarityTable) -> None:
    """The wheels know nothing of the kidnap (their step at the jump is an ordinary one):
    the images must win against the odometry. Headings come from the odometry once the
    fit has seen enough travel, and follow the robot's."""
    r = run(small_map, table, sunny2, "dpso", seed=0, start=0, kidnap=True, odometry=True)
    assert frames_to_recover(r) is not None, "the kidnap was not recovered"
    truth = small_world.round_trajectory(1, len(sunny2))[0][:, 2]
    assert r.heading_sources is not None
    half = len(r.frames) // 2
    use = [k for k in range(20, half) if r.heading_sources[k] == "odometry"
           and r.status[k] == "tracking"]
    assert len(use) > half // 2
    err = np.degrees(np.abs(np.angle(np.exp(1j * (r.heading[use] - truth[r.frames[use]])))))
    assert np.median(err) < 10.0


@pytest.mark.parametrize("estimator", ["pf-l", "pf-g"])
def test_the_particle_filters_localize_with_odometry(small_map: RouteMap, sunny2: Round,
                                                      table: SimilarityTable,
                                                      estimator: str) -> None:
    """Each particle carries its own heading offset (service/estimators/particle_filter.py):
    with the wheels the filter does at least as well as without. One heading fitted from
    the filter's own estimates and shared by every particle moved the whole cloud off the
    route (7.0 m on this round, against 1.0 m without)."""
    errors = []
    for odo in (False, True):
        r = run(small_map, table, sunny2, estimator, seed=0, start=0, odometry=odo)
        errors.append(float(np.linalg.norm(r.est_xy - r.true_xy, axis=1)[20:].mean()))
    assert errors[1] <= errors[0] < 1.5, errors


def test_the_wheels_see_an_ordinary_step_at_a_jump() -> None:
    odom = np.column_stack([np.arange(10) * 0.6, np.zeros(10), np.zeros(10)])
    poses = odometry_along(odom, np.array([2, 3, 4, 8, 9, 0, 1]))
    steps = np.diff(poses[:, 0])
    assert np.allclose(steps, 0.6)  # the kidnap 4 -> 8 and the wrap 9 -> 0 included


def test_a_round_reads_its_odometry_and_refuses_a_mismatched_one(rounds_dir, tmp_path) -> None:
    rnd = read_round(rounds_dir / "sunny2")
    assert rnd.odometry is not None and rnd.odometry.shape == (len(rnd), 3)
    bad = tmp_path / "r"
    bad.mkdir()
    for name in ("poses.csv", rnd.images[0], rnd.images[1]):
        (bad / name).write_bytes((rnd.path / name).read_bytes())
    (bad / "poses.csv").write_text(f"image,x,y\n{rnd.images[0]},0,0\n{rnd.images[1]},1,0\n")
    (bad / "odometry.csv").write_text(f"image,x,y,yaw\n{rnd.images[1]},0,0,0\n")
    with pytest.raises(DatasetError, match="same images in the same order"):
        read_round(bad)


def test_http_frames_carry_odometry_and_bad_odometry_is_refused(server, sunny2: Round
                                                                ) -> None:
    url, robot = server["url"], "odo-http"
    assert sunny2.odometry is not None
    with httpx.Client(base_url=url, timeout=60) as c:
        assert c.put(f"/sessions/{robot}", json={"seed": 3}).status_code in (200, 201)

        def frame(i: int, **q: object) -> httpx.Response:
            return c.post(f"/sessions/{robot}/frames", params={"t": float(i), **q},
                          content=sunny2.image_path(i).read_bytes(),
                          headers={"Content-Type": "image/png"})

        for i in range(4):
            x, y, yaw = sunny2.odometry[i]
            r = frame(i, odom_x=x, odom_y=y, odom_yaw=yaw, odom_var_xy=0.01)
            assert r.status_code == 200, r.text
            assert r.json()["heading_source"] in ("motion", "odometry")
        frames = c.get(f"/sessions/{robot}").json()["frames"]
        for q, words in [({"odom_x": 1.0, "odom_y": 2.0}, "missing odom_yaw"),
                         ({"odom_x": "nan", "odom_y": 0, "odom_yaw": 0}, "finite"),
                         ({"odom_x": 1e5, "odom_y": 0, "odom_yaw": 0}, "more than 100 m"),
                         ({"odom_var_yaw": 0.1}, "variances need")]:
            r = frame(4, **q)
            assert r.status_code == 422 and words in r.text, (q, r.text)
        assert c.get(f"/sessions/{robot}").json()["frames"] == frames  # untouched
        x, y, yaw = sunny2.odometry[4]
        assert frame(4, odom_x=x, odom_y=y, odom_yaw=yaw).json()["seq"] == frames + 1
        c.delete(f"/sessions/{robot}")


def test_a_located_position_the_odometry_contradicts_waits_for_a_second_one() -> None:
    """One located position far from the odometry's prediction moves nothing; the next one
    within the distance travelled since (heading-free: after a kidnap the odometry's map
    heading is wrong) is taken, as a move."""
    gate, pred = LocatedGate(), np.array([10.0, 0.0])
    assert gate.admit(np.array([10.8, 0.3]), pred, 0.6, 1.5)  # within the gate
    assert not gate.moved
    assert not gate.admit(np.array([14.0, 0.0]), pred, 0.6, 1.5)  # a lone contradiction
    # the second agrees, 0.6 m on in a direction the odometry's heading does not give
    assert gate.admit(np.array([14.0, -0.6]), pred, 0.6, 1.5)
    assert gate.moved and gate.pending is None
    # two contradictions that disagree with each other: both held back
    assert not gate.admit(np.array([20.0, 0.0]), pred, 0.6, 1.5)
    assert not gate.moved
    assert not gate.admit(np.array([5.0, 3.0]), pred, 0.6, 1.5)
    # a held-back position is forgotten after keep_frames frames
    for _ in range(LocatedGate.keep_frames + 1):
        assert gate.admit(None, pred, 0.6, 1.5)
    assert gate.pending is None
    assert not gate.admit(np.array([20.0, 0.0]), pred, 0.6, 1.5)
    # off, or no prediction yet (the reported position restarted): taken
    assert gate.admit(np.array([50.0, 0.0]), pred, 0.6, 0.0)
    assert gate.admit(np.array([50.0, 0.0]), None, 0.6, 1.5)


def test_a_move_made_by_a_look_alike_is_undone_by_the_track_before_it() -> None:
    """Regression (seed 11, cloudy frames 66-78): two frames in a row located 0.35 m apart
    at a look-alike 5.4 m behind the odometry's prediction were taken as a move, and the
    estimate stayed 4-6 m off for ten frames although a located frame on the old track came
    four frames later. For ``keep_frames`` frames after a move, a located frame on the track
    the odometry carried before it (moved by the same steps) undoes the move."""
    step = np.array([0.6, 0.0])
    gate, pred = LocatedGate(), np.array([10.0, 0.0])
    assert not gate.admit(np.array([4.6, 0.0]), pred, 0.6, 1.5)  # the look-alike
    pred = pred + step
    assert gate.admit(np.array([4.9, 0.2]), pred, 0.6, 1.5) and gate.moved  # again: a move
    new = np.array([4.9, 0.2])  # the reported position restarts there
    for _ in range(2):  # two frames not located, both tracks carried by the odometry
        new, pred = new + step, pred + step
        assert gate.admit(None, new, 0.6, 1.5)
    new, pred = new + step, pred + step
    # located on the old track, 5.6 m from the new one: the move is undone
    assert gate.admit(pred + np.array([0.3, -0.2]), new, 0.6, 1.5) and gate.moved
    # nor one older than keep_frames frames
    gate, pred = LocatedGate(), np.array([10.0, 0.0])
    assert not gate.admit(np.array([4.6, 0.0]), pred, 0.6, 1.5)
    assert gate.admit(np.array([4.9, 0.2]), pred, 0.6, 1.5) and gate.moved
    for _ in range(LocatedGate.keep_frames):
        assert gate.admit(None, new, 0.6, 1.5)
    assert not gate.admit(pred, new, 0.6, 1.5)


def test_a_gate_stored_before_the_undo_still_admits_frames() -> None:
    """A durable session written by the version before the undo: its gate's state has no
    ``undo`` (the state codec sets only the stored attributes); it goes on working."""
    from service.engine.state_codec import dumps, loads

    old = LocatedGate()
    del old.undo, old.undo_age  # what that version stored
    back = loads(dumps({"gate": old}))["gate"]
    pred = np.array([10.0, 0.0])
    assert back.admit(pred + 0.2, pred, 1.0, 1.5)
    assert not back.admit(pred + 5.0, pred, 1.0, 1.5)  # held back, as before
    assert back.admit(pred + 5.5, pred, 1.0, 1.5) and back.moved  # the second agrees: a move


def _carried_track(small_map: RouteMap, sunny2: Round, table: SimilarityTable,
                   params: dict) -> tuple[np.ndarray, list[str]]:
    """Errors (m) and statuses of a DPSO run over sunny2 with its odometry whose frames
    40-47 match every map image alike (a stretch the map does not show)."""
    assert sunny2.odometry is not None
    loc = Localizer(small_map, "dpso", params, seed=0)
    errors, status = [], []
    for k in range(48):
        x, y, yaw = (float(v) for v in sunny2.odometry[k])
        step = loc.take_odometry(Odometry(x=x, y=y, yaw=yaw))
        sim = partial(table.scores, k) if k < 40 else (lambda ids: np.full(len(ids), 0.02))
        res = loc.estimator.step(sim, float(k), None, step)
        errors.append(float(np.linalg.norm(res.position - sunny2.reference_xy[k])))
        status.append(res.status.value)
    return np.asarray(errors), status


def test_the_odometry_carries_the_position_while_no_match_stands_out(
        small_map: RouteMap, sunny2: Round, table: SimilarityTable) -> None:
    """Where no map image stands out the place is lost and the swarm searches the map; the
    reported position is the one the images last gave, moved by the wheels
    (``odom_carry_frames``), not the search's (``odom_carry_frames`` 0)."""
    errors, status = _carried_track(small_map, sunny2, table, {})
    assert status[39] == "tracking" and "recovering" in status[40:]
    assert errors[39] < 2.0
    assert errors[40:].max() < errors[39] + 1.0  # 8 frames of odometry drift, no jump
    search, _ = _carried_track(small_map, sunny2, table, {"odom_carry_frames": 0})
    assert search[40:].max() > errors[40:].max() + 1.0  # the search's estimate wanders


def test_a_jump_restarts_the_odometry_map_heading() -> None:
    """After a kidnap the map heading fitted at the old place is wrong: ``restart`` drops it
    (and its pairs), so the direction of motion stands in until a new fit."""
    h = OdomHeading()
    for k in range(12):  # a straight drive east, located along a path heading north
        h.advance(OdomStep(1.0, 0.0, 0.0, 0.0, 0.0))
        h.observe(np.array([0.0, float(k + 1)]))
    heading, _ = h.heading(None)
    assert heading is not None and heading == pytest.approx(math.pi / 2, abs=1e-6)
    h.restart()
    assert h.heading(0.3) == (0.3, pytest.approx(math.radians(20.0)))
    assert len(h.pairs) == 0
