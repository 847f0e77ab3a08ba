"""The night-places study (client/lab/night_places.py): whole-image thumbnails, SeqSLAM's
sum along the route, and how a round's frames are placed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from client.dataset import Round
from client.lab.night_places import (
    along_odometry,
    along_sequence,
    chance,
    differences,
    placed,
    study,
    thumbnail,
    tracked,
)

SIZE = (64, 48)
BLOCK = 8


def test_a_thumbnail_does_not_see_the_light_s_gain_and_offset(sunny1: Round) -> None:
    img = sunny1.load_image(5)
    grey = img if img.ndim == 2 else img.mean(axis=2)
    base = thumbnail(grey.astype(np.float32), SIZE, BLOCK)
    dim = thumbnail(0.1 * grey.astype(np.float32) + 3.0, SIZE, BLOCK)
    assert base.shape == (SIZE[0] * SIZE[1],)
    assert float(np.abs(base - dim).mean()) < 0.01  # the same patches, normalised
    other = thumbnail(sunny1.load_image(len(sunny1) // 2), SIZE, BLOCK)
    assert float(np.abs(base - other).mean()) > 0.3  # another place is another thumbnail
    with pytest.raises(ValueError, match="multiple of the block"):
        thumbnail(img, (60, 48), BLOCK)


def test_the_sequence_sums_along_the_route() -> None:
    rng = np.random.default_rng(3)
    diff = rng.random((12, 20))
    seq = along_sequence(diff, 4)
    assert np.isinf(seq[:3]).all()
    # frame 7 at image 9: frames 4..7 at images 6..9
    assert seq[7, 9] == pytest.approx(diff[7, 9] + diff[6, 8] + diff[5, 7] + diff[4, 6])
    # the map wraps around its loop: frame 5 at image 1 reaches back to image 19
    assert seq[5, 1] == pytest.approx(diff[5, 1] + diff[4, 0] + diff[3, 19] + diff[2, 18])
    assert np.array_equal(along_sequence(diff, 1), diff)
    with pytest.raises(ValueError):
        along_sequence(diff, 0)


def test_a_noisy_route_is_found_along_its_sequence() -> None:
    """Frame i belongs at image i + 5; each frame alone is mostly lost in noise, the sum
    over ten frames finds the diagonal."""
    rng = np.random.default_rng(0)
    n, m = 60, 80
    diff = rng.normal(1.0, 0.3, (n, m))
    diff[np.arange(n), np.arange(n) + 5] -= 0.3
    image_xy = np.column_stack([np.arange(m) * 1.0, np.zeros(m)])
    frame_xy = image_xy[np.arange(n) + 5]
    alone = placed(diff, image_xy, frame_xy)
    ten = placed(along_sequence(diff, 10), image_xy, frame_xy)
    assert ten.frames == n - 9
    assert ten.near > 0.9 > 0.6 > alone.near


def test_dark_noisy_frames_are_placed_by_their_thumbnails(sunny1: Round,
                                                          sunny2: Round) -> None:
    """A second round of the route, darkened to a tenth and noised (a night of sorts): the
    thumbnails place most frames within 3 m, far more often than chance."""
    rng = np.random.default_rng(1)
    images = np.stack([thumbnail(sunny1.load_image(i), SIZE, BLOCK)
                       for i in range(len(sunny1))])
    frames = []
    for i in range(len(sunny2)):
        img = sunny2.load_image(i).astype(np.float32)
        dark = np.clip(0.1 * img + rng.normal(0.0, 2.0, img.shape), 0, 255).astype(np.uint8)
        frames.append(thumbnail(dark, SIZE, BLOCK))
    p = placed(differences(np.stack(frames), images), np.asarray(sunny1.reference_xy),
               np.asarray(sunny2.reference_xy))
    luck = chance(np.asarray(sunny1.reference_xy), np.asarray(sunny2.reference_xy))
    assert p.frames == len(sunny2)
    assert p.near > 0.5 and p.near > 10 * luck, (p, luck)


def test_the_wheels_carry_the_belief_to_where_the_frames_agree() -> None:
    """Frame i belongs at image (2 i + 7) mod M: the robot drives two map spacings a frame.
    Each frame alone is mostly lost in noise; the forward filter, moved by the odometry's
    travel (with a 3 % scale error), finds and keeps the place. Moved by nothing (the wheels
    ignored) it is lost again."""
    rng = np.random.default_rng(4)
    n, m, spacing = 150, 120, 0.6
    truth = (2 * np.arange(n) + 7) % m
    diff = rng.normal(1.0, 0.3, (n, m))
    diff[np.arange(n), truth] -= 0.5
    image_xy = np.column_stack([np.arange(m) * spacing, np.zeros(m)])
    travel = np.full(n - 1, 2 * spacing * 1.03)
    def near(best: np.ndarray) -> float:  # the share of frames 40 on within one image
        off = np.abs(best - truth) % m
        return float(np.mean(np.minimum(off, m - off)[40:] <= 1))

    best = along_odometry(diff, travel, spacing, tau=0.3)
    assert near(best) > 0.85
    assert near(diff.argmin(axis=1)) < 0.4  # each frame alone
    assert near(along_odometry(diff, np.zeros(n - 1), spacing, tau=0.3)) < 0.3
    result = tracked(best, image_xy, image_xy[truth])
    assert result.within_5m > 0.7 and result.mean_m < 10
    with pytest.raises(ValueError, match="odometry steps"):
        along_odometry(diff, travel[:-1], spacing, tau=0.3)
    with pytest.raises(ValueError, match="positive"):
        along_odometry(diff, travel, spacing, tau=0.0)


def test_a_map_of_layers_takes_each_place_s_closest_layer(rounds_dir: Path) -> None:
    """A map of two rounds ('+') in which one is the query round itself: its own images win
    at every place, so every frame is placed within 3 m, where the other round alone places
    fewer; the round's odometry drives the filter column."""
    one = study(rounds_dir, 3, "cloudy1", "sunny2", SIZE, BLOCK, [1], 0, "clahe-rootsift")
    both = study(rounds_dir, 3, "cloudy1+sunny2", "sunny2", SIZE, BLOCK, [1], 0,
                 "clahe-rootsift")
    assert both.thumbnails[1].near == 1.0 > one.thumbnails[1].near
    assert both.odometry is not None and both.odometry.within_5m > 0.9
    assert one.local is None  # every=0: the local features not measured
