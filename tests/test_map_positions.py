"""Map image positions fused with wheel odometry (service/maps/positions.py): closer to the
truth than GPS-like poses, the recorded ones kept where asked or where the odometry does
not fit, and the map's own position error as the floor of a located frame's radius. A
learning robot's taught frames are placed the same way with the odometry it sent
(service/engine/learning.py)."""

from __future__ import annotations

import io
import math
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from client.dataset import Round
from service.engine.learning import placed, smoothed
from service.engine.localizer import Localizer
from service.maps.experiences import NewImage
from service.maps.positions import (
    FUSED_SIGMA_M,
    MAX_MOVED_M,
    fuse_with_odometry,
    round_positions,
)
from service.maps.route_map import build_map_from_rounds


def _route(n: int = 400, step: float = 0.6) -> np.ndarray:
    """(n, 3) x, y, heading of a drive: straight, a 90-degree curve of 12 m radius, straight."""
    turn = np.zeros(n)
    turn[120:152] = (math.pi / 2) / 32  # 32 steps of 0.6 m: a 19 m arc, radius ~12 m
    heading = np.cumsum(turn)
    xy = np.cumsum(np.stack([np.cos(heading), np.sin(heading)], 1) * step, axis=0)
    return np.column_stack([xy, heading])


def _gps(truth: np.ndarray, rng: np.random.Generator, sigma: float = 0.3,
         rho: float = 0.9) -> np.ndarray:
    """GPS-like positions: the truth plus noise correlated from image to image (AR(1))."""
    e = np.empty((len(truth), 2))
    e[0] = rng.normal(0, sigma, 2)
    for k in range(1, len(truth)):
        e[k] = rho * e[k - 1] + rng.normal(0, sigma * math.sqrt(1 - rho**2), 2)
    return truth[:, :2] + e


def _odometry(truth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Wheel odometry in its own frame: 3 % too long, drifting 0.1 degree per metre, noisy."""
    steps = np.diff(truth[:, :2], axis=0) * 1.03
    drift = np.cumsum(np.radians(0.1) * np.linalg.norm(steps, axis=1)
                      + rng.normal(0, np.radians(0.1), len(steps)))
    c, s = np.cos(drift + 0.7), np.sin(drift + 0.7)  # any starting heading
    turned = np.column_stack([c * steps[:, 0] - s * steps[:, 1],
                              s * steps[:, 0] + c * steps[:, 1]])
    start = np.array([5.0, -3.0])
    return np.vstack([start, start + np.cumsum(turned, axis=0)])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fused_positions_are_closer_to_the_truth_than_gps_like_ones(seed: int) -> None:
    rng = np.random.default_rng(seed)
    truth = _route()
    gps, odom = _gps(truth, rng), _odometry(truth, rng)
    fused = fuse_with_odometry(gps, odom)
    before = np.linalg.norm(gps - truth[:, :2], axis=1).mean()
    after = np.linalg.norm(fused.xy - truth[:, :2], axis=1).mean()
    assert after < 0.75 * before, (before, after)
    assert fused.fits and fused.moved_m < MAX_MOVED_M
    # the curve keeps its shape: no image of it is pulled off by the straight parts
    assert np.linalg.norm(fused.xy - truth[:, :2], axis=1)[110:160].max() < 0.8


def _taught(seed: int) -> tuple[np.ndarray, list[NewImage], list[int], list[np.ndarray | None]]:
    """A learning robot's 40 taught frames along the drive (every fourth image, a curve among
    them): the truth, the images at their located positions (the geometry's error, 0.4 m per
    axis) and the frame numbers and odometry it sent with them."""
    rng = np.random.default_rng(seed)
    truth = _route()
    odom = _odometry(truth, rng)
    idx = np.arange(60, 220, 4)
    located = truth[idx, :2] + rng.normal(0, 0.4, (len(idx), 2))
    images = [NewImage(np.zeros((2, 4), np.uint8), np.zeros((2, 2), np.float32), xy, f"e/{k}")
              for k, xy in zip(idx, located, strict=True)]
    return truth[idx, :2], images, [int(k) for k in idx], [o for o in odom[idx]]


def _error(images: list[NewImage], truth: np.ndarray) -> float:
    return float(np.linalg.norm(np.array([f.xy for f in images]) - truth, axis=1).mean())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_taught_frames_are_placed_along_the_odometry_the_robot_sent(seed: int) -> None:
    truth, images, seqs, odom = _taught(seed)
    located, line = _error(images, truth), _error(smoothed(images, seqs), truth)
    fused = _error(placed(images, seqs, odom), truth)
    assert fused < 0.6 * located and fused < line, (located, line, fused)


def test_images_without_a_position_are_placed_by_their_odometry_alone() -> None:
    """``known``: only those rows' recorded positions align the odometry. Stretches of 20
    images whose recorded positions are garbage are placed by the odometry between the known
    ones as well as the known ones are; used as recorded they would pull the fit off; an image
    with no known one in its window gets NaN."""
    rng = np.random.default_rng(4)
    truth = _route()
    gps, odom = _gps(truth, rng), _odometry(truth, rng)
    known = np.ones(len(truth), bool)
    for start in (60, 130, 250):
        known[start:start + 20] = False
    garbage = np.where(known[:, None], gps, gps + 25.0)
    err = np.linalg.norm(fuse_with_odometry(garbage, odom, known=known).xy - truth[:, :2],
                         axis=1)
    assert float(err[~known].mean()) < max(0.35, 1.5 * float(err[known].mean())), err
    blind = np.linalg.norm(fuse_with_odometry(garbage, odom).xy - truth[:, :2], axis=1)
    assert float(blind[~known].mean()) > 5.0
    lone = np.zeros(len(truth), bool)
    lone[:3] = True  # three known images at the start, nothing near the end
    far = fuse_with_odometry(gps, odom, known=lone).xy
    assert np.isfinite(far[:10]).all() and np.isnan(far[-10:]).all()


def test_taught_frames_without_odometry_or_with_odometry_that_does_not_fit_are_smoothed(
) -> None:
    _, images, seqs, odom = _taught(3)
    line = [f.xy for f in smoothed(images, seqs)]
    missing = [None, *odom[1:]]  # one frame came without it
    feet = [o * 3.28 for o in odom]
    for sent in (missing, feet, [None] * len(odom), []):  # [], a collection kept without
        assert np.array_equal([f.xy for f in placed(images, seqs, sent)], line)
    assert not np.array_equal([f.xy for f in placed(images, seqs, odom)], line)


def test_a_robot_standing_still_takes_the_mean_of_its_positions() -> None:
    rng = np.random.default_rng(3)
    gps = rng.normal(0, 0.3, (40, 2)) + np.array([10.0, 20.0])
    fused = fuse_with_odometry(gps, np.zeros((40, 2)))
    assert np.allclose(fused.xy, gps.mean(axis=0))


def test_odometry_of_another_drive_or_in_other_units_is_not_used(sunny1: Round) -> None:
    rng = np.random.default_rng(4)
    truth = _route()
    gps = _gps(truth, rng)
    angle = np.arange(len(truth)) * 0.6 / 4.0  # circles of 4 m radius, 0.6 m a step
    circles = np.column_stack([4 * np.cos(angle), 4 * np.sin(angle)])
    assert not fuse_with_odometry(gps, circles).fits
    feet = _odometry(truth, rng) / 0.3048
    assert not fuse_with_odometry(gps, feet).fits
    assert sunny1.odometry is not None
    xy, how = round_positions(replace(sunny1, odometry=sunny1.odometry / 0.3048))
    assert np.array_equal(xy, sunny1.xy) and how.startswith("recorded (the odometry")
    cut = replace(sunny1, images=sunny1.images[:4], xy=sunny1.xy[:4])  # odometry of all
    assert round_positions(cut)[1] == "recorded (the odometry lists other images)"


def test_a_rendered_round_s_fused_positions_are_closer_to_its_truth(sunny1: Round) -> None:
    assert sunny1.odometry is not None and sunny1.truth_xy is not None
    xy, how = round_positions(sunny1)
    assert how.startswith("fused with odometry")
    before = np.linalg.norm(sunny1.xy - sunny1.truth_xy, axis=1).mean()
    after = np.linalg.norm(xy - sunny1.truth_xy, axis=1).mean()
    assert after < 0.8 * before, (before, after)
    assert np.array_equal(round_positions(sunny1, "recorded")[0], sunny1.xy)
    with pytest.raises(ValueError, match="unknown positions rule"):
        round_positions(sunny1, "smoothed")  # type: ignore[arg-type]


def test_a_map_keeps_how_its_positions_were_made_and_localizes_with_their_error(
        sunny1: Round) -> None:
    part = sunny1.subset(range(0, 24, 2))
    fused = build_map_from_rounds([part], name="fused")
    xy, how = round_positions(part)
    assert np.allclose(fused.positions, xy) and not np.allclose(fused.positions, part.xy)
    assert fused.meta["source"]["positions"] == [how]
    assert fused.position_sigma_m == FUSED_SIGMA_M
    assert Localizer(fused, "dpso").params["metric_map_sigma_m"] == FUSED_SIGMA_M
    assert Localizer(fused, "dpso", {"metric_map_sigma_m": 0.5}).params[
        "metric_map_sigma_m"] == 0.5  # the session's own choice stands
    recorded = build_map_from_rounds([part], name="recorded", positions="recorded")
    assert np.allclose(recorded.positions, part.xy)
    assert recorded.meta["source"]["positions"] == ["recorded"]
    assert recorded.position_sigma_m is None
    assert Localizer(recorded, "dpso").params["metric_map_sigma_m"] == 0.28
    no_odometry = build_map_from_rounds([replace(part, odometry=None)], name="plain")
    assert np.allclose(no_odometry.positions, part.xy)


def _zip(rnd: Round, odometry: str | None) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("r/poses.csv", "image,x,y\n" + "".join(
            f"{rnd.images[i]},{rnd.xy[i][0]},{rnd.xy[i][1]}\n" for i in range(3)))
        for i in range(3):
            zf.write(rnd.image_path(i), f"r/{rnd.images[i]}")
        if odometry is not None:
            zf.writestr("r/odometry.csv", odometry)
    return buf.getvalue()


def test_an_uploaded_round_brings_its_odometry_or_a_clear_error(tmp_path: Path,
                                                                sunny1: Round) -> None:
    from service.api.errors import InvalidParameters
    from service.maps.round_archive import ArchiveLimits, UploadedRound, extract_round

    def upload(name: str, odometry: str | None) -> UploadedRound:
        (tmp_path / f"{name}.zip").write_bytes(_zip(sunny1, odometry))
        return extract_round(tmp_path / f"{name}.zip", tmp_path / name, ArchiveLimits())

    rows = "".join(f"{sunny1.images[i]},{0.6 * i},0.0,0.0\n" for i in range(3))
    rnd = upload("good", "image,x,y,yaw\n" + rows)
    assert rnd.odometry is not None and np.allclose(rnd.odometry[:, 0], [0.0, 0.6, 1.2])
    assert upload("none", None).odometry is None
    with pytest.raises(InvalidParameters, match=r"odometry.csv, line 3: x, y and yaw"):
        upload("bad", "image,x,y,yaw\n" + rows.replace("0.6,", "north,", 1))


@pytest.mark.parametrize("command", ["build", "build-remote"])
def test_an_unknown_positions_rule_is_one_line(command: str, sunny1: Round) -> None:
    from typer.testing import CliRunner

    from client.cli import app

    where = ["--out", "/nonexistent/m"] if command == "build" else ["--to", "http://127.0.0.1:9"]
    res = CliRunner().invoke(app, ["map", command, str(sunny1.path), *where,
                                   "--positions", "smoothed"])
    assert res.exit_code == 2
    assert "--positions must be one of fused, recorded, got 'smoothed'" in res.output
