from __future__ import annotations

import json
import math

import numpy as np

from client.lab.world import Pose, World
from service.vision.features import extract, similarity


def test_same_pose_renders_identically(small_world: World) -> None:
    pose = Pose(*small_world.round_trajectory(0)[0][10])
    a = small_world.render(pose, "sunny", t=3.0, noise_seed=7)
    b = small_world.render(pose, "sunny", t=3.0, noise_seed=7)
    assert a.shape == (240, 320) and a.dtype == np.uint8
    assert np.array_equal(a, b)
    assert a.std() > 20  # a textured street view, not a flat image


def test_world_is_deterministic_by_seed() -> None:
    pose = Pose(0.0, -10.0, 0.0)
    w1, w2, w3 = World(11, 80.0), World(11, 80.0), World(12, 80.0)
    a, b, c = (w.render(pose, "cloudy") for w in (w1, w2, w3))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_conditions_differ(small_world: World) -> None:
    pose = Pose(*small_world.round_trajectory(0)[0][5])
    sunny = small_world.render(pose, "sunny").astype(float)
    cloudy = small_world.render(pose, "cloudy").astype(float)
    assert np.abs(sunny - cloudy).mean() > 8


def test_round_geometry(small_world: World) -> None:
    poses, t, _ = small_world.round_trajectory(1)
    steps = np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1)
    assert 0.45 < np.median(steps) < 0.75  # one frame every ~0.6 m
    assert np.all(np.diff(t) > 0)
    # one round drives about once around the loop (speed varies a few per cent)
    assert abs(steps.sum() - small_world.route.length) < 0.15 * small_world.route.length
    # and stays on the road: within a few metres of the route centre line
    _, lateral = small_world.route.project(poses[:, :2])
    assert np.all(np.abs(lateral) < 3.0)


def test_neighbouring_frames_match_far_frames_do_not(small_world: World) -> None:
    poses, t, _ = small_world.round_trajectory(0)
    n = len(poses)
    feats = {i: extract(small_world.render(Pose(*poses[i]), "sunny", t=t[i], noise_seed=i))
             for i in (0, 1, 2, n // 2, n // 2 + 1)}
    assert min(len(f) for f in feats.values()) > 100
    near = similarity(feats[0].descriptors, feats[1].descriptors)
    near2 = similarity(feats[n // 2].descriptors, feats[n // 2 + 1].descriptors)
    far = similarity(feats[0].descriptors, feats[n // 2].descriptors)
    assert near > 0.15 and near2 > 0.15
    assert far < 0.05
    assert far < near / 4


def test_rendered_round_is_a_valid_dataset(sunny1) -> None:
    assert len(sunny1) > 100
    assert sunny1.truth_xy is not None and sunny1.t is not None
    gps_err = np.linalg.norm(sunny1.xy - sunny1.truth_xy, axis=1)
    assert 0.05 < gps_err.mean() < 1.0  # GPS-like noise around the exact positions
    assert sunny1.load_image(0).shape == (240, 320)


def test_render_takes_the_image_size(tmp_path) -> None:
    """`swarmloc world render --width --height`: frames of that size, the camera recorded
    with it."""
    from typer.testing import CliRunner

    from client.cli import app
    from client.dataset import read_round

    out = tmp_path / "w"
    res = CliRunner().invoke(app, ["world", "render", str(out), "--seed", "3", "--length",
                                   "12", "--rounds", "sunny1", "--width", "96",
                                   "--height", "72"])
    assert res.exit_code == 0, res.output
    rnd = read_round(out / "sunny1")
    assert rnd.load_image(0).shape == (72, 96)
    meta = json.loads((out / "dataset.json").read_text())
    assert (meta["camera"]["width"], meta["camera"]["height"]) == (96, 72)
    # the intrinsics are kept in image fractions: the same field of view at any size
    assert rnd.camera is not None and abs(rnd.camera["fx"] - 0.5 / math.tan(
        math.radians(meta["camera"]["hfov_deg"]) / 2)) < 1e-9
