"""Experience maps: layers the fleet learns (service/maps/experiences.py, engine/learning.py).

The map format keeps experiences as layers with their metadata (each change a new, verified
version); localization matches each particle with one layer; a learning session teaches only
where it is confidently right, and a session that is confidently wrong by construction teaches
nothing.
"""

from __future__ import annotations

import dataclasses
import logging
import re
import shutil
import threading
from pathlib import Path

import numpy as np
import pytest

from client.dataset import Round
from client.lab.world import World
from client.runs import odometry_poses
from client.transports import LocalClient
from service.api.errors import Conflict, NotFound
from service.api.models import (
    Estimate,
    LearningInfo,
    MapSummary,
    Odometry,
    PosePrior,
    SessionConfig,
    SessionInfo,
)
from service.api.round_format import camera_from_hfov
from service.engine.geometry_warmer import warm_order
from service.engine.learning import OUTCOMES, Learner, LearnGates, LearnPath, path_gate
from service.engine.localization_service import LocalizationService
from service.engine.localizer import Localizer
from service.maps.experiences import (
    BASE,
    GAP_SPACINGS,
    SEED_SHARE,
    LayerChoice,
    NewImage,
    add_experience,
    base_spacing,
    carry_geometry,
    compatible,
    experience_layers,
    experience_list,
    remove_experience,
    same_light_level,
)
from service.maps.route_map import RouteMap, load_map, save_map
from service.settings import Settings
from service.vision.features import Features, extract
from service.vision.map_geometry import GeometryParams
from service.vision.metric_pose import Camera
from tests.pose_builds import count_pose_builds

STRETCH = 60  # cloudy frames the map-format tests use (a stretch of the round)
LEARN_FRAMES = 30  # frames a learning session sends (the start of the round)
# test settings: a commit every few taught frames (over the stretch: two while the session
# runs, a few images left for its end), and a gate 1 that the short stretch passes
LEARN = {"learn_commit_images": 7, "learn_accuracy_m": 2.0}


@pytest.fixture(scope="module")
def cloudy_features(small_map: RouteMap, cloudy1: Round) -> list[Features]:
    return [extract(cloudy1.load_image(i), small_map.feature_params) for i in range(STRETCH)]


@pytest.fixture(scope="module")
def cloudy_images(cloudy_features: list[Features], cloudy1: Round) -> list[NewImage]:
    return [NewImage(f.codes, f.keypoints, np.asarray(cloudy1.xy[i], float), f"cloudy/{i}")
            for i, f in enumerate(cloudy_features)]


@pytest.fixture
def map_copy(small_map: RouteMap, tmp_path: Path) -> RouteMap:
    assert small_map.path is not None
    shutil.copy(small_map.path, tmp_path / "small.swmap")
    return load_map(tmp_path / "small.swmap")


def test_an_experience_is_a_new_verified_version_with_its_layer(
        map_copy: RouteMap, cloudy_images: list[NewImage]) -> None:
    assert experience_list(map_copy) == []  # a map from before experiences loads unchanged
    old_sum = map_copy.meta["checksum"]
    assert map_copy.path is not None
    new, retired = add_experience(map_copy, map_copy.path, "e1", cloudy_images[:20],
                                  condition="cloudy", robot="r1", now=1.0e9,
                                  budget_bytes=1 << 30)
    assert retired == []
    again = load_map(map_copy.path, verify=True)  # written atomically, checksummed
    assert again.meta["checksum"] == new.meta["checksum"] != old_sum
    assert compatible(again, old_sum) and not compatible(again, "0" * 64)
    (e,) = experience_list(again)
    assert (e["id"], e["condition"], e["robot"], e["layer"]) == ("e1", "cloudy", "r1", 1)
    assert e["images"] == int(np.sum(again.layers == 1)) > 0
    assert again.n_images == map_copy.n_images + e["images"]
    # the base images keep their ids and contents; the place index covers the new images
    assert np.array_equal(again.codes_of(5), map_copy.codes_of(5))
    assert again.place_index is not None and again.place_index.n_images == again.n_images


def test_one_image_per_place_and_experience(map_copy: RouteMap,
                                            cloudy_images: list[NewImage]) -> None:
    assert map_copy.path is not None
    a, _ = add_experience(map_copy, map_copy.path, "e1", cloudy_images[:10], condition=None,
                          robot=None, now=1.0, budget_bytes=1 << 30)
    same = [NewImage(f.codes, f.keypoints, f.xy + 0.05, f.name + "b") for f in
            cloudy_images[:10]]
    b, _ = add_experience(a, map_copy.path, "e1", same, condition=None, robot=None, now=2.0,
                          budget_bytes=1 << 30)
    assert b is a  # every place already has its image in e1: nothing written
    c, _ = add_experience(a, map_copy.path, "e2", same, condition=None, robot=None, now=3.0,
                          budget_bytes=1 << 30)
    assert experience_list(c)[1]["images"] == experience_list(c)[0]["images"]


def test_budget_retires_the_least_used_experience(map_copy: RouteMap,
                                                  cloudy_images: list[NewImage]) -> None:
    assert map_copy.path is not None
    a, _ = add_experience(map_copy, map_copy.path, "used", cloudy_images[0:20],
                          condition=None, robot=None, now=1.0, budget_bytes=1 << 30)
    b, _ = add_experience(a, map_copy.path, "idle", cloudy_images[20:40], condition=None,
                          robot=None, now=2.0, budget_bytes=1 << 30)
    size = {e["id"]: e["bytes"] for e in experience_list(b)}
    budget = size["used"] + size["idle"] + 1000  # room for the two, not for a third
    c, retired = add_experience(b, map_copy.path, "new", cloudy_images[40:60],
                                condition=None, robot=None, now=3.0, budget_bytes=budget,
                                usage={"used": (12, 2.5)})
    assert retired == ["idle"]
    kept = {e["id"]: e for e in experience_list(c)}
    assert set(kept) == {"used", "new"} and kept["used"]["uses"] == 12
    assert sum(e["bytes"] for e in kept.values()) <= budget
    assert sorted(e["layer"] for e in kept.values()) == [1, 2]  # renumbered, 0..L-1
    assert c.n_images == map_copy.n_images + kept["used"]["images"] + kept["new"]["images"]
    gone = remove_experience(c, map_copy.path, "used")
    assert list(experience_layers(gone)) == ["new"] and experience_layers(gone)["new"] == 1
    assert load_map(map_copy.path).n_images == map_copy.n_images + kept["new"]["images"]


def test_particles_match_one_layer_and_the_session_moves_to_todays_light(
        map_copy: RouteMap, cloudy_images: list[NewImage],
        cloudy_features: list[Features]) -> None:
    assert map_copy.path is not None
    learned, _ = add_experience(map_copy, map_copy.path, "cloudy", cloudy_images,
                                condition="cloudy", robot=None, now=1.0, budget_bytes=1 << 30)
    for k in range(3):  # more experiences (the same frames a little aside): no more work
        shifted = [NewImage(f.codes, f.keypoints, f.xy + 0.1 * (k + 1), f.name)
                   for f in cloudy_images[::2]]
        learned, _ = add_experience(learned, map_copy.path, f"other{k}", shifted,
                                    condition=None, robot=None, now=2.0, budget_bytes=1 << 30)
    assert learned.n_layers == 5
    frames = cloudy_features[:40]
    taught = Localizer(learned, seed=1)
    fitness: list[int] = []
    step = taught.estimator.step

    def counted(*args, **kw):  # the estimator's own comparisons, before the layer probes
        res = step(*args, **kw)
        fitness.append(res.comparisons)
        return res

    taught.estimator.step = counted  # type: ignore[method-assign]
    after, searching = [], []
    for i, f in enumerate(frames):
        searching.append(taught.estimator.wants_places())
        after.append(taught.step(f, t=float(i)))
    assert taught.choice.active == "cloudy" and after[-1].experience == "cloudy"
    assert taught.choice.scores["cloudy"] > taught.choice.scores[BASE]
    # each particle is compared with one image, whatever the number of layers ...
    ids, _ = taught.choice.nearest(learned)(learned.positions[:50])
    assert ids.shape == (50, 1)
    # ... the probes add at most two comparisons a frame, and while the swarm searches the
    # learned places proposed to it at most half the place candidates, whatever the layers
    extra = np.array([e.comparisons for e in after]) - np.array(fitness)
    search = np.array(searching)
    assert taught.seeder is not None and search.any() and not search.all()
    assert extra.min() >= 0 and extra[~search].max() <= 2
    assert extra[search].max() <= 2 + taught.seeder.k // 2


def test_a_frame_compares_no_more_images_on_an_experience_than_on_the_map_alone(
        map_copy: RouteMap, cloudy_images: list[NewImage],
        cloudy_features: list[Features]) -> None:
    """Issue #34's bound on comparisons: with an experience active, each particle's place is
    its nearest base image, and that image's nearest experience image stands in for it. So a
    swarm compares at most as many distinct images as on the base images alone (before this,
    the experience image nearest to each particle: the base images of the particles beyond
    the experience and the experience's own, 2-31 % more comparisons per frame on the rendered
    worlds). Checked on swarm-like clouds of particles, and over a replay."""
    assert map_copy.path is not None
    learned, _ = add_experience(map_copy, map_copy.path, "cloudy", cloudy_images,
                                condition="cloudy", robot=None, now=1.0, budget_bytes=1 << 30)
    layers = learned.layers
    assert layers is not None
    exp_layer = experience_layers(learned)["cloudy"]
    rng = np.random.default_rng(0)
    used = 0
    for i in range(5, len(cloudy_images) - 5, 5):
        at = cloudy_images[i].xy
        on = LayerChoice(active="cloudy").nearest(learned, at)
        off = LayerChoice().nearest(learned, at)
        for spread in (0.5, 2.0, 6.0):
            cloud = at + rng.normal(0, spread, (80, 2))
            ids, dist = on(cloud)
            base_ids, _ = off(cloud)
            assert len(np.unique(ids)) <= len(np.unique(base_ids)), (i, spread)
            np.testing.assert_allclose(
                dist[:, 0], np.linalg.norm(cloud - learned.positions[ids[:, 0]], axis=1))
            used += int(np.sum(layers[ids[:, 0]] == exp_layer))
    assert used > 0  # the experience's images are used
    plain = Localizer(map_copy, seed=1)
    taught = Localizer(learned, seed=1)
    frames = cloudy_features[:40]
    base = [plain.step(f, t=float(i)).comparisons for i, f in enumerate(frames)]
    after = [taught.step(f, t=float(i)) for i, f in enumerate(frames)]
    assert after[-1].experience == "cloudy"
    assert np.mean([e.comparisons for e in after]) <= 1.2 * np.mean(base)


def test_an_experience_on_a_lane_beside_the_maps_is_used_there(
        map_copy: RouteMap, cloudy_images: list[NewImage]) -> None:
    """Issue #34 (seed 23: the sunny map was recorded 1.2-2.1 m beside the lane the cloudy
    rounds drive, farther than the gap of two map spacings): an experience learned on today's
    lane covers the places of the map's images beside it. Particles on that lane are compared
    with its images (the rule before: only where the map's image itself lay within the gap of
    one, so an experience of every frame at its true place was not used there: 0.58 m, now
    0.14 m), and the frame still compares no more distinct images than on the map alone."""
    assert map_copy.path is not None
    # each cloudy frame placed 1.5 gaps beside the map's image of its place
    place, _ = map_copy.nearest_in_layer(np.array([f.xy for f in cloudy_images], float), 0)
    tangent = np.gradient(map_copy.positions, axis=0)[place]
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    gap = GAP_SPACINGS * base_spacing(map_copy)
    beside = [dataclasses.replace(f, xy=map_copy.positions[i] + 1.5 * gap * n)
              for f, i, n in zip(cloudy_images, place, normal, strict=True)]
    learned, _ = add_experience(map_copy, map_copy.path, "cloudy", beside,
                                condition="cloudy", robot=None, now=1.0, budget_bytes=1 << 30)
    layers = learned.layers
    assert layers is not None
    exp_layer = experience_layers(learned)["cloudy"]
    exp_xy = learned.positions[layers == exp_layer]
    # the experience's images lie farther than the gap from every image of the map's own
    assert float(np.min(learned.nearest_in_layer(exp_xy, 0)[1])) > gap
    rng = np.random.default_rng(0)
    for i in range(5, len(beside) - 5, 5):
        at = beside[i].xy
        cloud = at + rng.normal(0, 0.3, (80, 2))  # a swarm on today's lane
        ids, dist = LayerChoice(active="cloudy").nearest(learned, at)(cloud)
        base_ids, _ = LayerChoice().nearest(learned, at)(cloud)
        mine = layers[ids[:, 0]] == exp_layer
        assert mine.mean() > 0.9, i
        assert len(np.unique(ids)) <= len(np.unique(base_ids)), i
        np.testing.assert_allclose(
            dist[:, 0], np.linalg.norm(cloud - learned.positions[ids[:, 0]], axis=1))
        # particles on the map's own lane, far from today's, keep the map's images
        far = learned.positions[base_ids[:, 0]]
        far_ids, _ = LayerChoice(active="cloudy").nearest(learned, at)(far[:5])
        assert not np.any(layers[far_ids[:, 0]] == exp_layer), i
    # beside, not beyond: an image across the path from a map image shows its place, one
    # farther than the gap along the path (past the end of a gap of the experience) does not
    b = np.array([100])
    t = np.gradient(map_copy.positions, axis=0)[100]
    t = t / np.linalg.norm(t)
    across, along = np.array([-t[1], t[0]]) * 3 * gap, t * 1.5 * gap
    probe = np.concatenate([learned.positions, map_copy.positions[b] + [across, along]])
    extra = dataclasses.replace(learned, positions=probe)
    n = len(learned.positions)
    spacing = base_spacing(map_copy)
    assert LayerChoice._beside(extra, b, np.array([n]), spacing, gap).tolist() == [True]
    assert LayerChoice._beside(extra, b, np.array([n + 1]), spacing, gap).tolist() == [False]


@pytest.fixture(scope="module")
def camera_maps(tmp_path_factory: pytest.TempPathFactory, small_map: RouteMap,
                small_world: World) -> Path:
    """A maps directory with the sunny map and the world's camera (the geometry gate runs):
    the session's map with the intrinsics in its metadata, as a build from the round with a
    dataset.json camera gives."""
    d = tmp_path_factory.mktemp("exp_maps")
    cam = small_world.camera
    camera = Camera.from_dict(camera_from_hfov(cam.hfov_deg, cam.width, cam.height)).as_dict()
    route = dataclasses.replace(small_map, name="route", meta={**small_map.meta,
                                                               "camera": camera})
    assert load_map(save_map(route, d / "route"), verify=True).geometry is not None
    return d


def _service(camera_maps: Path, tmp_path: Path) -> LocalizationService:
    d = tmp_path / "maps"
    shutil.copytree(camera_maps, d)
    return LocalizationService(Settings(maps_dir=d, session_store="memory", **LEARN))


@dataclasses.dataclass(frozen=True)
class LearningRun:
    old: str  # the map's version before
    during: str  # its version while the session still runs (after a commit)
    stats: dict[str, int]
    summary: MapSummary  # after the session ended
    on_disk: RouteMap
    learning: LearningInfo | None  # GET /sessions/r1's progress after the last frame
    counted: dict[str, float]  # swarmloc_learning_frames_total by outcome
    other: SessionInfo  # a session on the same map that does not learn


def _learn(camera_maps: Path, tmp: Path, cloudy1: Round, odometry: bool,
           frames: int = LEARN_FRAMES) -> LearningRun:
    """One learning session over the start of the cloudy round (``frames`` frames), sent with
    the round's wheel odometry or without."""
    service = _service(camera_maps, tmp)
    old = str(service.get_map("route").meta["checksum"])
    service.put_session("r1", SessionConfig(map="route", learn=True, condition="cloudy"))
    service.put_session("r2", SessionConfig(map="route"))
    assert cloudy1.odometry is not None
    poses = odometry_poses(cloudy1.odometry if odometry else None, np.arange(frames))
    for i in range(frames):
        service.process_frame("r1", cloudy1.image_path(i).read_bytes(), t=float(i),
                              odom=poses[i])
    learning = service.session_info("r1").learning  # waits for the queued gates
    stats = service.learner.stats("r1")
    counted = {o: service.metrics.registry.get_sample_value(
        "swarmloc_learning_frames_total", {"outcome": o}) or 0.0 for o in OUTCOMES}
    other = service.session_info("r2")
    assert service.writer.wait(120)  # the full collections were handed to the writer
    during = str(service.map_summary("route").checksum)
    service.delete_session("r1")  # the images collected since the last commit are written
    assert service.writer.wait(120)
    summary = service.map_summary("route")
    path = service.get_map("route").path
    assert path is not None
    on_disk = load_map(path, verify=True)
    service.close()
    return LearningRun(old, during, stats, summary, on_disk, learning, counted, other)


@pytest.fixture(scope="module")
def learning_run(camera_maps: Path, tmp_path_factory: pytest.TempPathFactory,
                 cloudy1: Round) -> LearningRun:
    """One learning session over the start of the cloudy round (shared by the tests)."""
    return _learn(camera_maps, tmp_path_factory.mktemp("learn"), cloudy1, odometry=False)


def test_a_learning_session_teaches_its_map_a_new_version(learning_run: LearningRun,
                                                          cloudy1: Round) -> None:
    run = learning_run
    assert run.stats["seen"] == LEARN_FRAMES
    assert run.stats["taught"] > LEARN["learn_commit_images"], run.stats
    assert run.stats["odometry"] == 0  # sent without: the taught images are smoothed
    assert run.during != run.old  # a full collection is written while the session runs
    # the end of the session writes the images still waiting (a new version), if any
    assert (run.summary.checksum != run.during) == (run.stats["waiting"] > 0)
    (e,) = run.summary.experiences  # one session, one experience
    assert e.condition == "cloudy" and e.robot == "r1" and 0 < e.images <= run.stats["taught"]
    m = run.on_disk  # the file on disk is it
    assert m.meta["checksum"] == run.summary.checksum
    mask = m.layers == e.layer
    assert int(mask.sum()) == e.images
    assert float(np.max(np.abs(m.positions[mask] - _truth(cloudy1, m.image_names, mask)))) < 3.0


def test_a_learning_session_shows_what_it_taught(learning_run: LearningRun) -> None:
    """GET /sessions/{id}'s ``learning`` and the metrics count every frame once: taught, or
    stopped by one gate (a bridged frame was stopped first); a session that does not learn
    shows none."""
    run, lr = learning_run, learning_run.learning
    assert lr is not None and run.other.learning is None and not run.other.learn
    assert lr.frames == run.stats["seen"] == LEARN_FRAMES
    assert lr.taught == run.stats["taught"] > 0 and lr.bridged == run.stats["bridged"]
    assert lr.collected == run.stats["waiting"]
    assert lr.taught + sum(lr.stopped.values()) == lr.frames, lr
    assert lr.stopped and set(lr.stopped) <= set(OUTCOMES) - {"taught", "bridged"}
    (e,) = run.summary.experiences  # its images went into the experience it named
    assert e.id == lr.experience
    assert run.counted["taught"] == lr.taught and run.counted["bridged"] == lr.bridged
    assert all(run.counted[g] == n for g, n in lr.stopped.items())
    assert sum(run.counted.values()) == lr.frames + lr.bridged


def _teach_with_gaps(m: RouteMap, cloudy1: Round, feats: list[Features], gaps: list[range],
                     odometry: list[Odometry | None], reset_at: int | None = None,
                     weak_ratio: float = 0.4) -> tuple[list[NewImage], dict[str, int]]:
    """A learner fed the cloudy stretch at its true places, the frames of ``gaps`` stopped at
    gate 1 (the session not tracking there), each frame sent with ``odometry``; the session
    reset before frame ``reset_at``; gate 3 at ``weak_ratio``."""
    written: list[NewImage] = []
    learner = Learner(LearnGates(accuracy_m=1.5, weak_ratio=weak_ratio, commit_images=1000),
                      lambda _m, _e, images, _c, _r, _b, out=written: out.extend(images))
    for i, f in enumerate(feats):
        x, y = (float(v) for v in cloudy1.reference_xy[i])
        e = Estimate(seq=i + 1, stamp=None, frame_id="m", estimator="dpso", x=x, y=y,
                     heading=0.0, speed=0.0, status="tracking", lost=False, score=0.5,
                     comparisons=1, covariance=[[0.1, 0], [0, 0.1]],
                     pose_covariance=[0.0] * 36, accuracy_m=0.5, nearest_image=0,
                     nearest_image_name="x", spread_m=0.1)
        stopped = "confident" if any(i in g for g in gaps) else None
        if i == reset_at:
            learner.flush("r", reset=True)
        learner.observe("r", 0.0, "cloudy", m, f, e, stopped, odometry[i])
    stats = learner.stats("r")
    learner.flush("r", end=True)
    return written, stats


def _seqs(images: list[NewImage]) -> list[int]:
    """The frames (0-based) a learner's images were taught from (their names' numbers)."""
    return [int(f.name.rsplit("/", 1)[1]) - 1 for f in images]


def _carried(poses: list[Odometry | None], a: int, b: int, at: int
             ) -> list[tuple[np.ndarray, list[Odometry | None]]]:
    """The odometry of a robot carried 6 m along its way (from frame ``a`` to ``b``), or 5 m
    across it, before frame ``at``, unseen by its wheels: (the carry, the odometry)."""
    pa, pb = poses[a], poses[b]
    assert pa is not None and pb is not None
    ahead = np.array([pb.x - pa.x, pb.y - pa.y]) / float(np.hypot(pb.x - pa.x, pb.y - pa.y))
    return [(carry, [p if p is None or i < at else
                     p.model_copy(update={"x": p.x - float(carry[0]), "y": p.y - float(carry[1])})
                     for i, p in enumerate(poses)])
            for carry in (6.0 * ahead, 5.0 * np.array([-ahead[1], ahead[0]]))]


def test_a_robot_sending_its_odometry_teaches_images_placed_along_it(
        camera_maps: Path, cloudy1: Round, cloudy_features: list[Features]) -> None:
    """A learner fed the cloudy stretch at its true places (gates 3 and 4 run for real: the
    geometry locates each taught frame), once with the round's wheel odometry and once
    without: the frames located are taught both times (with the odometry also frames the
    wheels bridge), and with the odometry their positions (its path aligned to the located
    ones, learning.placed) are closer to the truth than the line through the located
    positions."""
    m = load_map(camera_maps / "route.swmap")
    assert cloudy1.odometry is not None
    poses = odometry_poses(cloudy1.odometry, np.arange(STRETCH))
    line_fit, _ = _teach_with_gaps(m, cloudy1, cloudy_features, [], [None] * STRETCH)
    names = {f.name for f in line_fit}
    along_fit = [f for f in _teach_with_gaps(m, cloudy1, cloudy_features, [], list(poses))[0]
                 if f.name in names]
    assert [f.name for f in line_fit] == [f.name for f in along_fit] and len(line_fit) >= 10
    truth = cloudy1.reference_xy[_seqs(line_fit)]
    line, along = (float(np.linalg.norm(np.array([f.xy for f in t]) - truth, axis=1).mean())
                   for t in (line_fit, along_fit))
    assert along < 0.7 * line, (line, along)


def test_frames_between_taught_ones_are_taught_by_the_wheels(
        camera_maps: Path, cloudy1: Round, cloudy_features: list[Features]) -> None:
    """Two stretches the session did not track (gate 1): with the robot's odometry their
    frames join the experience, placed by the wheels between the taught frames on either
    side (as close to the truth as those); without it none do, nor where the wheels disagree
    with where the taught frame after a stretch was located (the robot was carried off in it,
    along its way or across it)."""
    m = load_map(camera_maps / "route.swmap")
    assert cloudy1.odometry is not None
    poses = odometry_poses(cloudy1.odometry, np.arange(STRETCH))
    gaps = [range(20, 28), range(40, 46)]
    in_gap = [i for g in gaps for i in g]
    taught, stats = _teach_with_gaps(m, cloudy1, cloudy_features, gaps, list(poses))
    bridged = [f for f, i in zip(taught, _seqs(taught), strict=True) if i in in_gap]
    assert stats["bridged"] >= len(bridged) >= 8, stats  # most of the 14 (one per place)
    assert {i for i in _seqs(bridged)} & set(gaps[0]) and {i for i in _seqs(bridged)} & set(gaps[1])
    err = np.linalg.norm(np.array([f.xy for f in taught])
                         - cloudy1.reference_xy[_seqs(taught)], axis=1)
    on_wheels = np.isin(_seqs(taught), in_gap)
    assert float(err[on_wheels].mean()) < max(0.6, 1.5 * float(err[~on_wheels].mean())), err

    without, stats = _teach_with_gaps(m, cloudy1, cloudy_features, gaps, [None] * STRETCH)
    assert stats["bridged"] == 0 and not set(_seqs(without)) & set(in_gap)

    # carried 6 m ahead, or 5 m across its way (the distance between the taught frames on
    # either side barely changes), unseen by the wheels, in the middle of the first stretch
    for carry, carried in _carried(poses, 19, 28, 24):
        kidnapped, stats = _teach_with_gaps(m, cloudy1, cloudy_features, gaps, carried)
        assert not set(_seqs(kidnapped)) & set(gaps[0]), (carry, stats)


def test_a_carry_across_the_way_after_a_session_s_first_taught_frame_is_not_bridged(
        camera_maps: Path, cloudy1: Round, cloudy_features: list[Features]) -> None:
    """A stretch right after the first frame a session taught (one located frame before it:
    no path of taught frames to align the wheels to): the wheels' step, turned into the map
    by that frame's located camera heading, must reach the frame after the stretch. Without a
    carry the stretch is bridged; carried 5 m across its way in the middle (the distance
    between the taught frames on either side barely changes), none of it is."""
    m = load_map(camera_maps / "route.swmap")
    assert cloudy1.odometry is not None
    poses = odometry_poses(cloudy1.odometry, np.arange(STRETCH))
    first = min(_seqs(_teach_with_gaps(m, cloudy1, cloudy_features, [], list(poses))[0]))
    gap = range(first + 1, first + 9)
    taught, stats = _teach_with_gaps(m, cloudy1, cloudy_features, [gap], list(poses))
    assert stats["bridged"] > 0 and set(_seqs(taught)) & set(gap), stats

    _, carried = _carried(poses, first, gap.stop, first + 5)[1]  # 5 m across
    kidnapped, stats = _teach_with_gaps(m, cloudy1, cloudy_features, [gap], carried)
    assert not set(_seqs(kidnapped)) & set(gap), stats


def test_frames_before_a_session_s_first_taught_one_are_taught_by_the_wheels(
        camera_maps: Path, cloudy1: Round, cloudy_features: list[Features]) -> None:
    """The session's first 14 frames not tracked (gate 1: its start, a search): with the
    robot's odometry the wheels teach them back from the first taught frame, as far as each
    step seen by the images is the wheels' step, about as close to the truth as the taught
    frames; without the odometry none of them is taught. Where the robot was carried in the
    lead, unseen by its wheels (its first frames another place's, or its odometry missing a
    carry of 6 m along its way or 5 m across it), no frame before the carry is taught; nor
    any frame of the lead where the session was reset between it and the taught frames."""
    m = load_map(camera_maps / "route.swmap")
    assert cloudy1.odometry is not None
    poses = odometry_poses(cloudy1.odometry, np.arange(STRETCH))
    lead = range(0, 14)
    taught, stats = _teach_with_gaps(m, cloudy1, cloudy_features, [lead], list(poses))
    led = [i for i in _seqs(taught) if i in lead]
    assert len(led) >= 6 and min(led) <= 3 and stats["bridged"] >= len(led), (led, stats)
    assert _seqs(taught) == sorted(_seqs(taught))  # the experience's images in frame order
    err = np.linalg.norm(np.array([f.xy for f in taught])
                         - cloudy1.reference_xy[_seqs(taught)], axis=1)
    on_wheels = np.isin(_seqs(taught), led)
    assert float(err[on_wheels].mean()) < max(0.6, 1.5 * float(err[~on_wheels].mean())), err

    without, stats = _teach_with_gaps(m, cloudy1, cloudy_features, [lead], [None] * STRETCH)
    assert stats["bridged"] == 0 and not set(_seqs(without)) & set(lead), stats

    elsewhere = [cloudy_features[40 + i] for i in range(7)] + cloudy_features[7:]
    broken, _ = _teach_with_gaps(m, cloudy1, elsewhere, [lead], list(poses))
    assert not set(_seqs(broken)) & set(range(7)), _seqs(broken)

    for carry, carried in _carried(poses, 0, 14, 7):
        kidnapped, _ = _teach_with_gaps(m, cloudy1, cloudy_features, [lead], carried)
        assert not set(_seqs(kidnapped)) & set(range(7)), (carry, _seqs(kidnapped))

    reset, _ = _teach_with_gaps(m, cloudy1, cloudy_features, [lead], list(poses), reset_at=14)
    assert not set(_seqs(reset)) & set(lead) and set(_seqs(reset)) == set(_seqs(taught)) - set(led)


def test_the_service_hands_a_learning_robot_s_odometry_to_its_learner(
        camera_maps: Path, tmp_path: Path, cloudy1: Round) -> None:
    run = _learn(camera_maps, tmp_path, cloudy1, odometry=True, frames=12)
    assert run.stats["odometry"] == run.stats["taught"] > 0, run.stats


def test_a_learning_robot_is_answered_before_its_frames_teach(
        camera_maps: Path, tmp_path: Path, cloudy1: Round) -> None:
    """The gates run on the learner's threads: while they are held up (the test holds the
    learner's lock, which every observation takes) the robot's frames are answered; once they
    run, the statistics count every frame."""
    service = _service(camera_maps, tmp_path)
    service.put_session("r1", SessionConfig(map="route", learn=True, condition="cloudy"))
    answers: list[Estimate] = []

    def send() -> None:
        for i in range(4):
            answers.append(service.process_frame("r1", cloudy1.image_path(i).read_bytes(),
                                                 t=float(i)))

    robot = threading.Thread(target=send)
    with service.learner._lock:
        robot.start()
        robot.join(120)
        answered = not robot.is_alive()
    robot.join()
    assert answered and [a.seq for a in answers] == [1, 2, 3, 4]
    assert service.learner.stats("r1")["seen"] == 4
    service.close()
    assert not service.learner.running


def test_confirming_tracking_moves_no_estimate_on_a_learned_map(
        learning_run: LearningRun, cloudy1: Round) -> None:
    """``confirm_tracking`` is a report: on a map with an experience (the layer choice and
    its probes follow the swarm, not the report) the estimates are those without it, frame
    for frame, and only statuses differ. A gate of 1 mm confirms no place (the frames are
    the round's images shifted by 3 pixels, so that none is located exactly at the taught
    image of itself; with 1 cm, one frame's fix averaged with the map's own image's
    (engine/both_layers.py) lands 3 mm from its learned image and confirms the place): every
    frame the swarm tracks is reported recovering."""
    m = learning_run.on_disk
    feats = [extract(np.roll(cloudy1.load_image(i), 3, axis=1), m.feature_params)
             for i in range(LEARN_FRAMES)]
    runs = {}
    for confirm in (True, False):
        loc = Localizer(m, "dpso", {"confirm_tracking": confirm, "metric_gate_m": 0.001,
                                     "scout_unconfirmed": False},
                        seed=2)
        runs[confirm] = [loc.step(f, t=float(i)) for i, f in enumerate(feats)]
    on, off = runs[True], runs[False]
    assert [(e.x, e.y, e.experience) for e in on] == [(e.x, e.y, e.experience) for e in off]
    assert any(e.experience is not None for e in on)  # the experience is used
    changed = [(a.status, b.status) for a, b in zip(on, off, strict=True) if a.status != b.status]
    assert len(changed) >= 15 and all(c == ("recovering", "tracking") for c in changed)


def test_the_in_process_client_closes_the_engine_it_started(
        camera_maps: Path, tmp_path: Path, cloudy1: Round,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """``swarmloc replay --via local`` runs the engine in its own process: closing the client
    writes what a learning session left open collected (a run cut short) and stops the
    engine's background threads before the process exits."""
    monkeypatch.setenv("SWARMLOC_LEARN_ACCURACY_M", str(LEARN["learn_accuracy_m"]))
    d = tmp_path / "maps"
    shutil.copytree(camera_maps, d)
    client = LocalClient(d)
    client.create_session("r1", "route", learn=True, condition="cloudy")
    for i in range(LEARN_FRAMES):
        client.localize("r1", cloudy1.image_path(i).read_bytes(), t=float(i))
    taught = client.service.learner.stats("r1")["taught"]
    assert taught > 0
    assert experience_list(load_map(d / "route.swmap")) == []  # nothing written yet
    client.close()
    assert not client.service.warmer.running and not client.service.learner.running
    (e,) = experience_list(load_map(d / "route.swmap", verify=True))
    assert e["robot"] == "r1" and 0 < int(e["images"]) <= taught
    client.close()  # a second close changes nothing


def _truth(rnd: Round, names: list[str], mask: np.ndarray, first: int = 0) -> np.ndarray:
    """Where the images ``mask`` of ``names`` were taken: a session's estimate seq i + 1 is
    frame ``first + i`` of the round (a new localizer counts from 1)."""
    seq = [int(n.rsplit("/", 1)[1]) - 1 + first for n, k in zip(names, mask, strict=True) if k]
    return rnd.reference_xy[seq]


def feed_a_wrong_place(service: LocalizationService, map_name: str, sunny1: Round,
                       cloudy1: Round, frames: int) -> dict[str, int]:
    """A learning session fed ``frames`` cloudy frames, each with a forced prior half the
    route away from its place (confidently wrong by construction); its learner's gate counts,
    after the session is deleted."""
    service.put_session("liar", SessionConfig(map=map_name, learn=True, condition="cloudy"))
    xy, n = sunny1.xy, len(sunny1.xy)
    for i in range(frames):
        there = xy[(i + n // 2) % n]
        service.process_frame("liar", cloudy1.image_path(i).read_bytes(), t=float(i),
                              prior=PosePrior(x=float(there[0]), y=float(there[1]),
                                              radius=1.0))
    stats: dict[str, int] = service.learner.stats("liar")
    service.delete_session("liar")
    return stats


def test_a_session_confidently_wrong_by_construction_learns_nothing(
        camera_maps: Path, tmp_path: Path, sunny1: Round, cloudy1: Round) -> None:
    """Frames of one place with a forced prior half the route away: the estimator is held at
    the prior, and the gates (tracking, path, weak appearance, the geometry) refuse all."""
    service = _service(camera_maps, tmp_path)
    old = service.get_map("route").meta["checksum"]
    stats = feed_a_wrong_place(service, "route", sunny1, cloudy1, LEARN_FRAMES)
    assert stats["seen"] == LEARN_FRAMES and stats.get("taught", 0) == 0, stats
    assert sum(v for k, v in stats.items()
               if k not in ("seen", "taught", "bridged", "odometry", "waiting")) == \
        LEARN_FRAMES  # every frame stopped at a gate
    assert service.get_map("route").meta["checksum"] == old
    assert service.map_summary("route").experiences == []
    service.close()


def test_a_write_that_adds_nothing_keeps_the_experiences_uses(
        map_copy: RouteMap, cloudy1: Round, cloudy_images: list[NewImage]) -> None:
    """Regression: the uses counted since the map's last write (which the budget retires
    experiences by) were taken for every write, and lost where it wrote nothing: a batch
    whose places the experience already has (a robot's second lap, a batch written twice
    through Redis) or a write that failed. Now they are kept for the next write."""
    assert map_copy.path is not None
    add_experience(map_copy, map_copy.path, "e1", cloudy_images[:30], condition="cloudy",
                   robot=None, now=1.0, budget_bytes=1 << 30)
    service = LocalizationService(Settings(maps_dir=map_copy.path.parent,
                                           session_store="memory"))
    service.put_session("b", SessionConfig(map="small", seed=3))
    for i in range(20):
        service.process_frame("b", cloudy1.image_path(i).read_bytes(), t=float(i))

    def uses() -> int:
        return next(e.uses for e in service.map_summary("small").experiences if e.id == "e1")

    used = uses()
    assert used > 0
    version = service.map_summary("small").checksum
    service.writer.submit("small", "e1", cloudy_images[:5], "cloudy", "r")  # places it has
    assert service.writer.wait(60)
    assert service.map_summary("small").checksum == version  # nothing written ...
    assert uses() == used  # ... and nothing forgotten
    service.writer.submit("small", "e2", cloudy_images[30:35], "cloudy", "r")
    assert service.writer.wait(60)
    assert uses() == used and service.map_summary("small").checksum != version  # in the file
    service.close()


def test_deleting_an_experience_and_unknown_ones(map_copy: RouteMap, tmp_path: Path,
                                                 cloudy_images: list[NewImage]) -> None:
    assert map_copy.path is not None
    add_experience(map_copy, map_copy.path, "e1", cloudy_images[:10], condition=None,
                   robot=None, now=1.0, budget_bytes=1 << 30)
    service = LocalizationService(Settings(maps_dir=map_copy.path.parent,
                                           session_store="memory"))
    version = service.map_summary("small").checksum
    with pytest.raises(NotFound, match="no experience 'nope'"):
        service.admin.delete_experience("small", "nope")
    assert service.map_summary("small").checksum == version  # untouched
    summary = service.admin.delete_experience("small", "e1", if_match=f'"{version}"')
    assert summary.experiences == [] and summary.checksum != version
    assert summary.n_images == map_copy.n_images


def test_a_collection_is_not_written_into_a_map_rebuilt_meanwhile(
        camera_maps: Path, tmp_path: Path, cloudy1: Round,
        caplog: pytest.LogCaptureFixture) -> None:
    """Regression: a map replaced under its name (PUT of a rebuilt map) while a learning
    session still collected on the old one got the collection written into it, at the old
    map's positions (another map, another frame). Now the write is refused and logged, and
    the new map stays as it was; once the robot resets onto the new map it teaches it."""
    d = tmp_path / "maps"
    shutil.copytree(camera_maps, d)
    service = LocalizationService(Settings(maps_dir=d, session_store="memory",
                                           **{**LEARN, "learn_commit_images": 1000}))
    service.put_session("r1", SessionConfig(map="route", learn=True, condition="cloudy"))

    def send(frames: range) -> None:
        for i in frames:
            service.process_frame("r1", cloudy1.image_path(i).read_bytes(), t=float(i))

    send(range(12))
    assert service.learner.stats("r1")["waiting"] > 0
    old = service.get_map("route")  # rebuilt: the same route in another frame, 10 m east
    east = np.array([10.0, 0.0])
    rebuilt = save_map(dataclasses.replace(old, positions=old.positions + east),
                       tmp_path / "up" / "route")
    staged = service.admin.staging_file("upload")
    staged.write_bytes(rebuilt.read_bytes())
    service.admin.install_upload("route", staged)
    version = service.map_summary("route").checksum
    with caplog.at_level(logging.ERROR, "swarmloc"):
        service.learner.flush("r1")
        assert service.writer.wait(60)
    assert service.map_summary("route").checksum == version
    assert service.map_summary("route").experiences == []
    assert "not written" in caplog.text and "was replaced" in caplog.text
    service.reset_session("r1")  # onto the rebuilt map: its frames teach it
    send(range(12, 24))
    assert service.learner.stats("r1")["waiting"] > 0
    service.delete_session("r1")
    assert service.writer.wait(60)
    (e,) = service.map_summary("route").experiences
    m = service.get_map("route")
    mask = m.layers == e.layer  # placed in the new map's frame
    truth = _truth(cloudy1, m.image_names, mask, first=12) + east
    assert float(np.max(np.abs(m.positions[mask] - truth))) < 3.0
    service.close()


def test_a_running_session_moves_live_onto_its_map_s_new_experiences(
        map_copy: RouteMap, cloudy1: Round, cloudy_images: list[NewImage]) -> None:
    """A session keeps running, not reset, onto each new version of its map that differs only
    by experiences: another robot's learned light reaches it at its next frame, and a deleted
    experience leaves it on the map's own images. A learning session, and a session on a
    rebuilt map, wait for their reset."""
    assert map_copy.path is not None
    service = LocalizationService(Settings(maps_dir=map_copy.path.parent,
                                           session_store="memory"))
    service.put_session("b", SessionConfig(map="small", seed=3))
    service.put_session("teacher", SessionConfig(map="small", learn=True))

    def frame(i: int) -> Estimate:
        return service.process_frame("b", cloudy1.image_path(i).read_bytes(), t=float(i))

    before = [frame(i) for i in range(4)]
    v1 = service.session("b").info().map_checksum
    assert all(e.experience is None for e in before)
    service.admin.commit_experience("small", "e1", cloudy_images, "cloudy", "teacher")
    v2 = service.map_summary("small").checksum
    assert v2 != v1
    with pytest.raises(Conflict, match="older than the last"):  # a rejected frame moves nothing
        service.process_frame("b", cloudy1.image_path(4).read_bytes(), t=1.0)
    assert service.session("b").info().map_checksum == v1
    after = [frame(i) for i in range(4, 14)]
    info = service.session("b").info()
    assert info.map_checksum == v2 and info.frames == 14  # moved on, not started over
    assert [e.seq for e in after] == list(range(5, 15))
    assert abs(after[0].x - before[-1].x) < 3.0  # where the session was, not a new search
    assert any(e.experience == "e1" for e in after)  # matched with the learned light
    moved = service.metrics.sessions_moved
    assert moved._value.get() == 1
    # a learning robot never localizes against, nor is gated by, what it has just taught
    service.process_frame("teacher", cloudy1.image_path(0).read_bytes(), t=0.0)
    assert service.session("teacher").info().map_checksum == v1 and moved._value.get() == 1
    assert service.reset_session("teacher").map_checksum == v2

    service.admin.delete_experience("small", "e1")
    v3 = service.map_summary("small").checksum
    e = frame(14)
    assert e.experience is None and e.seq == 15
    assert service.session("b").info().map_checksum == v3 and moved._value.get() == 2

    rebuilt = load_map(map_copy.path)
    rebuilt.meta["checksum"] = "f" * 64  # as if the map had been rebuilt: not compatible
    service.admin.register(rebuilt, "upload")
    assert frame(15).seq == 16
    assert service.session("b").info().map_checksum == v3  # until the robot resets
    service.reset_session("b")
    assert service.session("b").info().map_checksum == "f" * 64
    service.close()


def test_a_session_follows_the_version_another_service_wrote(
        map_copy: RouteMap, sunny2: Round, cloudy_images: list[NewImage]) -> None:
    """Two services on one maps directory: the one that did not write the new version loads
    it in its periodic sweep (``expire_idle``), and its sessions move on at their next frame."""
    assert map_copy.path is not None
    writer, reader = (LocalizationService(Settings(maps_dir=map_copy.path.parent,
                                                   session_store="memory")) for _ in range(2))
    reader.put_session("b", SessionConfig(map="small"))

    def frame(i: int) -> Estimate:
        return reader.process_frame("b", sunny2.image_path(i).read_bytes(), t=float(i))

    frame(0)
    old = reader.session("b").info().map_checksum
    writer.admin.commit_experience("small", "e1", cloudy_images[:20], "cloudy", "teacher")
    new = writer.map_summary("small").checksum
    frame(1)
    assert reader.session("b").info().map_checksum == old  # not looked for on a frame's path
    reader.expire_idle()
    assert frame(2).seq == 3
    assert reader.session("b").info().map_checksum == new != old
    writer.close()
    reader.close()


def test_a_served_robot_follows_the_version_another_service_wrote(
        map_copy: RouteMap, sunny2: Round, cloudy_images: list[NewImage]) -> None:
    """Over a real uvicorn server: its periodic sweep (every second at this idle time) loads
    the version another service on the maps directory wrote, and a robot sending frames moves
    onto it without a reset."""
    import time

    from client.transports import HttpClient
    from service.server import free_port, running_server

    assert map_copy.path is not None
    writer = LocalizationService(Settings(maps_dir=map_copy.path.parent,
                                          session_store="memory"))
    reader = LocalizationService(Settings(maps_dir=map_copy.path.parent, port=free_port(),
                                          session_store="memory", session_idle_s=4.0))
    with running_server(reader, zenoh=False) as url:
        client = HttpClient(url)
        old = client.create_session("b", "small").map_checksum
        client.localize("b", sunny2.image_path(0).read_bytes(), t=0.0)
        writer.admin.commit_experience("small", "e1", cloudy_images[:20], "cloudy", "teacher")
        new = writer.map_summary("small").checksum
        seen, k, deadline = old, 1, time.monotonic() + 15.0
        while seen != new and time.monotonic() < deadline:
            time.sleep(0.3)
            assert client.localize("b", sunny2.image_path(k).read_bytes(), t=float(k)).seq \
                == k + 1  # never reset
            seen = client.session("b").map_checksum
            k += 1
        assert seen == new != old
        client.close()
    writer.close()


def test_robots_are_answered_while_a_map_is_written_or_a_learner_drains(
        map_copy: RouteMap, sunny2: Round, cloudy1: Round,
        cloudy_images: list[NewImage]) -> None:
    """Regression: over a real uvicorn server, requests that wait for a learner to drain
    (DELETE /sessions/{id} of a learning robot) or for the map admin (GET /maps/{name} while
    an experience is written: the writer holds the admin's lock for the whole write, and
    waits for another replica's write on the maps directory) ran on the event loop, so every
    robot's frames waited with them. Now they wait in a thread."""
    import fcntl
    import os
    import time

    import httpx

    from service.server import free_port, running_server

    assert map_copy.path is not None
    service = LocalizationService(Settings(maps_dir=map_copy.path.parent, port=free_port(),
                                           session_store="memory"))
    png = {"content-type": "image/png"}
    with running_server(service, zenoh=False) as url, httpx.Client(base_url=url,
                                                                   timeout=10) as http:
        assert http.put("/sessions/walker", json={"map": "small"}).status_code == 201
        assert http.put("/sessions/teacher", json={"map": "small", "learn": True}
                        ).status_code == 201

        def frame(robot: str, i: int, rnd: Round = sunny2) -> int:
            return http.post(f"/sessions/{robot}/frames", params={"t": float(i)},
                             content=rnd.image_path(i).read_bytes(), headers=png).status_code

        assert frame("walker", 0) == 200
        with service.learner._lock:  # the teacher's gates held up: its end waits for them
            assert frame("teacher", 0, cloudy1) == 200
            ended = threading.Thread(target=lambda: httpx.delete(f"{url}/sessions/teacher",
                                                                 timeout=60))
            ended.start()
            time.sleep(0.5)
            assert frame("walker", 1) == 200  # answered meanwhile
            assert ended.is_alive()
        ended.join(60)

        # another replica on the maps directory writes the map (holds its file lock) while
        # this one's writer has a learned batch for it: the writer waits, holding the admin
        lock = os.open(map_copy.path.with_name(".small.swmap.lock"), os.O_RDWR | os.O_CREAT)
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            service.writer.submit("small", "e1", cloudy_images[:5], "cloudy", "teacher")
            while service.admin._lock.acquire(blocking=False):  # until the writer holds it
                service.admin._lock.release()
                time.sleep(0.01)
            viewer = threading.Thread(target=lambda: httpx.get(f"{url}/maps/small",
                                                               timeout=60))
            viewer.start()
            time.sleep(0.5)  # the viewer's request waits for the admin
            assert frame("walker", 2) == 200  # answered meanwhile
            assert viewer.is_alive()
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
            os.close(lock)
        viewer.join(60)
        assert service.writer.wait(60)
        assert [e.id for e in service.map_summary("small").experiences] == ["e1"]
    service.close()


def test_a_new_version_keeps_the_structures_built_on_the_old_one(
        camera_maps: Path, tmp_path: Path, cloudy_images: list[NewImage],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The two-view structures and camera headings built on a version carry over to the next
    one (a session that moves on finds them built), and each is the one the new version would
    build itself; not where the image's partner changed, nor for an image that is gone."""

    shutil.copy(camera_maps / "route.swmap", tmp_path / "route.swmap")
    v0 = load_map(tmp_path / "route.swmap", verify="lazy")
    p = GeometryParams()
    v1, _ = add_experience(v0, tmp_path / "route.swmap", "e1", cloudy_images[:30:2],
                           condition="cloudy", robot=None, now=1.0, budget_bytes=1 << 30)
    g1 = v1.geometry
    assert g1 is not None
    g1.warm(range(v1.n_images), p)
    v2, _ = add_experience(v1, tmp_path / "route.swmap", "e1", cloudy_images[30::2],
                           condition="cloudy", robot=None, now=2.0, budget_bytes=1 << 30)
    assert carry_geometry(v1, v2) > 0.9 * v0.n_images
    g2 = v2.geometry
    assert g2 is not None
    carried = set(g2.cached())
    assert set(range(v0.n_images)) <= carried  # the map's own images: all kept
    fresh = load_map(tmp_path / "route.swmap", verify="lazy").geometry  # built anew
    assert fresh is not None
    for i in sorted(carried):
        a, b = g2.structure(i, p), fresh.structure(i, p)
        assert (a is None) == (b is None), i
        if a is not None and b is not None:
            assert np.array_equal(a.feature_ids, b.feature_ids) and \
                np.array_equal(a.points, b.points), i
    # the map's own images' headings come along: none needs a pair's pose built again, and
    # each is the one the new version builds itself
    own = [i for i in range(v0.n_images) if g2.structure(i, p) is not None]
    built = count_pose_builds(monkeypatch)
    headings = [g2.camera_heading(i, p) for i in own]
    assert own and built == []
    assert headings == [fresh.camera_heading(i, p) for i in own]
    # e1's images appended in the second write, further along, make a new partner for the
    # last of the first write's
    e1 = experience_layers(v1)["e1"]
    first = np.flatnonzero(np.asarray(v1.layers) == e1)
    moved = [i for i in first if g1.partner(int(i), p.baseline_m) != g2.partner(int(i),
                                                                                 p.baseline_m)]
    assert moved and not set(moved) & carried
    # and every heading on the new version, carried or not, is the one it builds itself
    for i in range(v2.n_images):
        assert g2.camera_heading(i, p) == fresh.camera_heading(i, p), i
    # removed: nothing of the experience is carried
    v3 = remove_experience(v2, tmp_path / "route.swmap", "e1")
    carry_geometry(v2, v3)
    assert v3.geometry is not None and set(v3.geometry.cached()) <= set(range(v0.n_images))
    # the warmer builds a version's learned images first, in the order they were taught
    order = warm_order(v2)
    learned = np.flatnonzero(np.asarray(v2.layers) == experience_layers(v2)["e1"])
    assert sorted(order.tolist()) == list(range(v2.n_images))
    assert order[: len(learned)].tolist() == learned.tolist() and learned[0] >= v0.n_images


def test_learner_gates_need_a_continuous_path() -> None:
    """Gate 2: a frame right after a jump (or the first frames) does not teach; a frame that
    is not confident (gate 1) clears the path."""

    def est(seq: int, x: float, status: str = "tracking") -> Estimate:
        return Estimate(seq=seq, stamp=None, frame_id="m", estimator="dpso", x=x, y=0.0,
                        heading=0.0, speed=0.0, status=status, lost=False, score=0.5,
                        comparisons=1, covariance=[[0.1, 0], [0, 0.1]],
                        pose_covariance=[0.0] * 36, accuracy_m=0.5, nearest_image=0,
                        nearest_image_name="x", spread_m=0.1)

    path: LearnPath = []
    stopped = []
    for e in (est(1, 0.0), est(2, 0.6), est(3, 1.2), est(4, 9.0), est(5, 9.6), est(6, 10.2),
              est(7, 10.8, "recovering"), est(8, 11.4), est(9, 12.0), est(10, 12.6)):
        path, gate = path_gate(path, e, 1.5)
        stopped.append(gate)
    # the first two frames have no path yet; the jump breaks it until two frames agree again
    assert stopped == ["path", "path", None, "path", "path", None, "confident", "path",
                       "path", None]


def test_a_tracked_frame_above_the_accuracy_gate_keeps_the_path() -> None:
    """Gate 1 on a tracked frame whose accuracy_m is above the gate: it stays on the path
    (gate 2 holds for the frames after it) and is stopped as ``accuracy``: it teaches only
    where the learner's own geometry locates it (Learner.observe)."""

    def est(seq: int, x: float, accuracy: float) -> Estimate:
        return Estimate(seq=seq, stamp=None, frame_id="m", estimator="dpso", x=x, y=0.0,
                        heading=0.0, speed=0.0, status="tracking", lost=False, score=0.5,
                        comparisons=1, covariance=[[0.1, 0], [0, 0.1]],
                        pose_covariance=[0.0] * 36, accuracy_m=accuracy, nearest_image=0,
                        nearest_image_name="x", spread_m=0.1)

    path: LearnPath = []
    stopped = []
    for e in (est(1, 0.0, 0.5), est(2, 0.6, 1.7), est(3, 1.2, 1.7), est(4, 1.8, 0.5)):
        path, gate = path_gate(path, e, 1.5)
        stopped.append(gate)
    assert stopped == ["path", "path", "accuracy", None]


def test_a_robot_behind_an_http_round_robin_teaches_its_map(
        camera_maps: Path, tmp_path: Path, cloudy1: Round, redis_srv, rdb) -> None:
    """Two replicas on one Redis store and one maps directory; the learning robot's frames
    alternate between them (an HTTP round robin). The path is kept with the stored session, so
    both replicas' frames pass gate 2 (before, each replica saw every other frame and taught
    nothing), and each writes what it collected into the one experience."""
    d = tmp_path / "maps"
    shutil.copytree(camera_maps, d)
    replicas = [LocalizationService(Settings(maps_dir=d, session_store=redis_srv.url,
                                             replica_id=f"r{k}", **LEARN)) for k in (0, 1)]
    try:
        replicas[0].put_session("rr", SessionConfig(map="route", learn=True))
        for i in range(LEARN_FRAMES):
            replicas[i % 2].process_frame("rr", cloudy1.image_path(i).read_bytes(), t=float(i))
        taught = [r.learner.stats("rr")["taught"] for r in replicas]
        assert all(n > 0 for n in taught), taught
        # each replica shows what it collected, into the one experience
        progress = [r.session_info("rr").learning for r in replicas]
        assert all(p is not None for p in progress)
        assert sum(p.frames for p in progress if p) == LEARN_FRAMES
        assert [p.taught for p in progress if p] == taught
        assert len({p.experience for p in progress if p}) == 1
        replicas[0].delete_session("rr")  # replica 0 writes its collection at the end ...
        replicas[1].learner.flush_idle(0.0)  # ... replica 1 once the robot left it
        for r in replicas:
            assert r.writer.wait(120)
        (e,) = replicas[1].map_summary("route").experiences
        m = replicas[1].get_map("route")
    finally:
        for r in replicas:
            r.close()
    seqs = {int(n.rsplit("/", 1)[1]) for n, k in zip(m.image_names, m.layers == e.layer,
                                                     strict=True) if k}
    assert {q % 2 for q in seqs} == {0, 1}, seqs  # frames served by each replica


def test_a_new_learning_session_starts_its_own_collection_on_every_replica(
        camera_maps: Path, tmp_path: Path, cloudy1: Round, redis_srv, rdb) -> None:
    """Regression: a replica that had served a learning robot kept the robot's collection
    after its session ended through another replica, and the robot's next learning session
    continued it there: the old session's experience, counts and images. Now a new session
    (a new experience) starts its own collection, and the old one is written into the old
    experience."""
    d = tmp_path / "maps"
    shutil.copytree(camera_maps, d)
    served, other = (LocalizationService(Settings(
        maps_dir=d, session_store=redis_srv.url, replica_id=f"r{k}",
        **{**LEARN, "learn_commit_images": 1000})) for k in (0, 1))
    try:
        other.put_session("rb", SessionConfig(map="route", learn=True))
        for i in range(12):
            served.process_frame("rb", cloudy1.image_path(i).read_bytes(), t=float(i))
        first = served.session_info("rb").learning
        assert first is not None and first.collected > 0
        other.delete_session("rb")  # ended through the other replica
        other.put_session("rb", SessionConfig(map="route", learn=True))  # a new session
        for i in range(12, 16):
            served.process_frame("rb", cloudy1.image_path(i).read_bytes(), t=float(i))
        second = served.session_info("rb").learning
        assert second is not None and second.experience != first.experience
        assert second.frames == 4 and second.taught <= 4
        assert served.writer.wait(60)
        (e,) = served.map_summary("route").experiences  # the first session's collection
        assert e.id == first.experience and e.images > 0
    finally:
        for r in (served, other):
            r.close()


def test_http_lists_and_deletes_experiences(map_copy: RouteMap, cloudy1: Round,
                                            cloudy_images: list[NewImage]) -> None:
    import httpx

    from client.transports import HttpClient, SwarmlocError
    from service.server import free_port, running_server

    assert map_copy.path is not None
    add_experience(map_copy, map_copy.path, "e1", cloudy_images[:10], condition="cloudy",
                   robot="r1", now=1.0e9, budget_bytes=1 << 30)
    service = LocalizationService(Settings(maps_dir=map_copy.path.parent, port=free_port(),
                                           session_store="memory"))
    with running_server(service, zenoh=False) as url:
        got = httpx.get(f"{url}/maps/small")
        etag = got.headers["ETag"]
        (e,) = got.json()["experiences"]
        assert (e["id"], e["condition"], e["images"], e["last_used"]) == \
            ("e1", "cloudy", 10, None)
        assert "experiences" not in got.json()["meta"]
        bad = httpx.put(f"{url}/sessions/r2", json={"map": "small", "learn": True,
                                                    "condition": "no spaces"})
        assert bad.status_code == 422 and "condition" in bad.text
        client = HttpClient(url)
        info = client.create_session("r2", "small", learn=True, condition="cloudy")
        assert info.learn and info.condition == "cloudy"
        with pytest.raises(SwarmlocError) as exc:
            client.delete_experience("small", "e1", if_match="0" * 64)
        assert exc.value.status == 412
        with pytest.raises(SwarmlocError) as exc:
            client.delete_experience("small", "e9")
        assert exc.value.status == 404 and "no experience 'e9'" in exc.value.message
        client.create_session("walker", "small")  # a robot driving meanwhile
        client.localize("walker", cloudy1.image_path(0).read_bytes(), t=0.0)
        after = client.delete_experience("small", "e1", if_match=etag.strip('"'))
        assert after.experiences == [] and f'"{after.checksum}"' != etag
        assert httpx.get(f"{url}/maps/small").headers["ETag"] == f'"{after.checksum}"'
        assert client.localize("walker", cloudy1.image_path(1).read_bytes(), t=1.0).seq == 2
        walker = client.session("walker")  # moved onto the new version, not reset
        assert walker.map_checksum == after.checksum and walker.frames == 2
        client.localize("r2", cloudy1.image_path(0).read_bytes(), t=0.0)
        r2 = client.session("r2")
        assert r2.map_checksum == etag.strip('"')  # learning: its version
        assert r2.learning is not None and r2.learning.frames == 1  # its progress
        assert r2.learning.taught + sum(r2.learning.stopped.values()) == 1
        assert walker.learning is None
        metrics = httpx.get(f"{url}/metrics").text
        assert 'swarmloc_learning_frames_total{outcome="' in metrics
        client.close()


def test_two_replicas_on_redis_one_writer_no_lost_update(
        map_copy: RouteMap, cloudy_images: list[NewImage], redis_srv, rdb, sunny2: Round
) -> None:
    """Two replicas on one maps directory and one Redis learn from two robots at once: their
    writers hand the batches over through Redis, one holds the map's writer lease and writes
    both, each onto the newest file, and both replicas serve the version with both."""
    import threading

    assert map_copy.path is not None
    replicas = [LocalizationService(Settings(maps_dir=map_copy.path.parent,
                                             session_store=redis_srv.url, replica_id=f"r{k}"))
                for k in (1, 2)]
    old = replicas[0].get_map("small").meta["checksum"]
    replicas[0].put_session("walker", SessionConfig(map="small"))
    replicas[0].process_frame("walker", sunny2.image_path(0).read_bytes(), t=0.0)
    go = threading.Barrier(2)

    def teach(k: int) -> None:
        go.wait()
        replicas[k].writer.submit("small", f"e{k}", cloudy_images[30 * k: 30 * k + 30],
                                  "cloudy", f"robot{k}")
        assert replicas[k].writer.wait(60)

    threads = [threading.Thread(target=teach, args=(k,)) for k in (0, 1)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    on_disk = load_map(map_copy.path, verify=True)
    assert sorted(experience_layers(on_disk)) == ["e0", "e1"]  # no lost update
    assert rdb.llen("swarmloc:learn:small") == 0 and rdb.get("swarmloc:writer:small") is None
    for r in replicas:  # both serve the new version
        s = r.map_summary("small")
        assert s.checksum == on_disk.meta["checksum"] != old
        assert sorted(e.id for e in s.experiences) == ["e0", "e1"]
    # the session stored on the first version continues on either replica, on the new one
    est = replicas[1].process_frame("walker", sunny2.image_path(1).read_bytes(), t=1.0)
    assert est.seq == 2
    assert replicas[1].session("walker").info().map_checksum == on_disk.meta["checksum"]
    for r in replicas:
        r.close()


def test_the_viewer_stream_names_the_experience() -> None:
    import json

    from service.engine.events import estimate_message

    est = Estimate(seq=1, stamp=None, frame_id="m", estimator="dpso", x=0.0, y=0.0,
                   heading=0.0, speed=0.0, status="tracking", lost=False, score=0.5,
                   comparisons=1, covariance=[[0.1, 0], [0, 0.1]], pose_covariance=[0.0] * 36,
                   accuracy_m=0.5, nearest_image=0, nearest_image_name="x", spread_m=0.1,
                   robot_id="r")
    assert "experience" not in json.loads(estimate_message(est, 0.0, None))
    learned = est.model_copy(update={"experience": "e1"})
    assert json.loads(estimate_message(learned, 0.0, None))["experience"] == "e1"


def test_replay_learn_through_the_local_transport(camera_maps: Path, tmp_path: Path,
                                                  cloudy1: Round,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    from typer.testing import CliRunner

    from client.cli import app

    for key, value in LEARN.items():  # the in-process service's settings
        monkeypatch.setenv(f"SWARMLOC_{key.upper()}", str(value))
    shutil.copytree(camera_maps, tmp_path / "maps")
    out = CliRunner().invoke(app, [
        "replay", str(cloudy1.path), "--map", "route", "--via", f"local:{tmp_path / 'maps'}",
        "--length", "20", "--learn", "--condition", "cloudy",
        "--out", str(tmp_path / "report")])
    assert out.exit_code == 0, out.output
    assert "map route: version" in out.output and "condition cloudy" in out.output
    taught = re.search(r"learning: (\d+) of 20 frames taught, (\d+) bridged", out.output)
    assert taught is not None, out.output
    m = load_map(tmp_path / "maps" / "route.swmap")
    (e,) = experience_list(m)
    assert e["condition"] == "cloudy" and e["robot"] == "replay"
    assert 0 < e["images"] <= int(taught.group(1)) + int(taught.group(2))


def _captured_nearest(loc: Localizer) -> list:
    """The ``nearest`` function the localizer gives its estimator, one per frame from now."""
    step = loc.estimator.step
    nearest_fns: list = []

    def captured(*args, **kw):
        nearest_fns.append(kw.get("nearest"))
        return step(*args, **kw)

    loc.estimator.step = captured  # type: ignore[method-assign]
    return nearest_fns


def test_in_a_gap_of_the_experience_every_particle_uses_the_base_images(
        map_copy: RouteMap, cloudy_images: list[NewImage],
        cloudy_features: list[Features], cloudy1: Round) -> None:
    """Issue #34 (seed 37): an experience learned on part of the route. Where the robot is in a
    gap of it, particles at the true place were scored on the base images (another light) while
    particles at the experience's images nearby got today's light: the swarm left the gap for
    the covered part and lost track. In a gap every particle now uses the base images."""
    assert map_copy.path is not None
    gapped = cloudy_images[:15] + cloudy_images[45:]  # no images for frames 15-44 (~18 m)
    learned, _ = add_experience(map_copy, map_copy.path, "cloudy", gapped,
                                condition="cloudy", robot=None, now=1.0, budget_bytes=1 << 30)
    exp_layer = experience_layers(learned)["cloudy"]
    loc = Localizer(learned, seed=1)
    nearest_fns = _captured_nearest(loc)
    est = [loc.step(f, t=float(i)) for i, f in enumerate(cloudy_features)]
    assert loc.choice.scores and est[14].experience == "cloudy"  # it learned today's light
    everywhere = learned.positions  # particles at every image of the map
    layers = learned.layers
    assert layers is not None
    for i in range(25, 35):  # frames deep in the gap
        assert np.hypot(est[i - 1].x - cloudy1.xy[i - 1][0],
                        est[i - 1].y - cloudy1.xy[i - 1][1]) < 2.0
        ids, _ = nearest_fns[i](everywhere)
        assert not np.any(layers[ids] == exp_layer), i
    # where the experience covers the estimate, its images are used again
    ids, _ = nearest_fns[55](everywhere)
    assert np.any(layers[ids] == exp_layer)


def test_a_searching_swarm_is_given_only_learned_places_its_frame_matches(
        map_copy: RouteMap, cloudy_images: list[NewImage],
        cloudy_features: list[Features], cloudy1: Round) -> None:
    """Issue #34 (maps of two feature types at dusk, seeds 0 and 37: 1.55 -> 8.51 m and
    1.12 -> 4.01 m): a session that starts where a partial experience has no images. The place
    index proposed the learned images (today's light looks more like any frame of that light
    than the map's own images at the true place), probes at the searching swarm's estimate
    moved the session to the experience, and the search settled at its images, 45 m off, for
    40 frames. While the swarm searches (no estimate yet, initializing or lost) the particles
    are compared with the map's own images and the layers are probed only at an estimate that
    tracks; the place index ranks the map's own images and the learned ones apart, and a
    searching swarm is given a learned image only where the frame matches it at
    ``SEED_SHARE`` of the map's same-light level (a start inside the experience's cover is
    then found in today's light: seed 0 dusk 3.05 -> 0.52 m)."""
    assert map_copy.path is not None
    learned, _ = add_experience(map_copy, map_copy.path, "cloudy", cloudy_images[30:],
                                condition="cloudy", robot=None, now=1.0, budget_bytes=1 << 30)
    exp_layer = experience_layers(learned)["cloudy"]
    layers = learned.layers
    assert layers is not None
    least = SEED_SHARE * same_light_level(learned)
    loc = Localizer(learned, seed=1)
    assert loc.seeder is not None and loc.seeder.learned is not None
    nearest_fns = _captured_nearest(loc)
    searched = refused = 0
    for i, f in enumerate(cloudy_features[:30]):  # frames 0-29: a gap of the experience
        before = loc.last
        searching = loc.estimator.wants_places()
        loc.step(f, t=float(i))
        ids = loc.seeder.last_ids
        mine = ids[layers[ids] == exp_layer]
        if searching:  # what the estimator was given: learned images only where they match
            searched += 1
            assert np.all(learned.similarity(f, mine) >= least), i
            ranked, _ = learned.place_index.query(f.codes, loc.seeder.k // 2,
                                                  loc.seeder.learned)
            refused += int(np.sum(learned.similarity(f, ranked) < least))
        if before is None or before.status not in ("tracking", "recovering"):
            ids, _ = nearest_fns[i](learned.positions)
            assert not np.any(layers[ids] == exp_layer), i
    assert searched > 0 and refused > 0  # in the gap, learned places were refused

    # a start inside the experience's cover is given its learned places, near the truth
    start = Localizer(learned, seed=1)
    assert start.estimator.wants_places()
    start.step(cloudy_features[45], t=0.0)
    assert start.seeder is not None
    ids = start.seeder.last_ids
    mine = ids[layers[ids] == exp_layer]
    assert len(mine) > 0
    truth = np.asarray(cloudy1.xy[45], float)
    assert float(np.min(np.linalg.norm(learned.positions[mine] - truth, axis=1))) < 5.0


def test_particles_compared_with_different_layers_compete_on_one_scale(
        map_copy: RouteMap, cloudy_images: list[NewImage]) -> None:
    """Issue #34 (the end of a dusk experience, seed 0): a learned image of today's light
    matches a frame of that light at a wrong place better than the map's own image at the true
    place, so particles near the learned images won where the experience ends. An experience
    image's similarity is put on the base layer's scale: times the base layer's running score
    over the experience's (both probed at the estimate); an experience that matches worse than
    the base is left as it is, and so is a session with nothing scored."""
    assert map_copy.path is not None
    learned, _ = add_experience(map_copy, map_copy.path, "cloudy", cloudy_images[30:],
                                condition="cloudy", robot=None, now=1.0, budget_bytes=1 << 30)
    layers = learned.layers
    assert layers is not None
    exp_ids = np.flatnonzero(layers == experience_layers(learned)["cloudy"])[:5]
    base_ids = np.flatnonzero(layers == 0)[:5]
    ids = np.concatenate([exp_ids, base_ids])

    def raw(i: np.ndarray) -> np.ndarray:
        return np.full(np.shape(i), 0.2)

    choice = LayerChoice(scores={BASE: 0.05, "cloudy": 0.5}, active="cloudy")
    assert np.allclose(choice.scaled(learned, raw)(ids), [0.02] * 5 + [0.2] * 5)
    choice.scores["cloudy"] = 0.04  # matches worse than the map's own images: unchanged
    assert np.allclose(choice.scaled(learned, raw)(ids), 0.2)
    assert np.allclose(LayerChoice().scaled(learned, raw)(ids), 0.2)
