"""A frame located at an experience image is located at the map's own image too
(service/engine/both_layers.py), with the real two-view geometry on a rendered world."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from client.dataset import Round
from service.engine.both_layers import AGREE_M, BothLayers
from service.engine.localizer import Localizer
from service.estimators.along_track import located_position
from service.maps.experiences import NewImage, add_experience, experience_layers
from service.maps.route_map import RouteMap, load_map
from service.vision.features import Features, extract
from service.vision.map_geometry import FramePairs, GeometryParams

FRAMES = range(10, 50)  # a stretch of the cloudy round: even frames learned, odd ones located


def _learned(camera_map: RouteMap, cloudy1: Round, feats: dict[int, Features], tmp: Path,
             beside_m: float) -> RouteMap:
    """The camera map with an experience of the stretch's even frames, each placed
    ``beside_m`` to the left of its true place (a learning robot's placement error)."""
    assert camera_map.path is not None
    shutil.copy(camera_map.path, tmp / "cam.swmap")
    m = load_map(tmp / "cam.swmap")
    truth = cloudy1.reference_xy
    images = []
    for i in FRAMES[::2]:
        t = truth[i + 1] - truth[i - 1]
        left = np.array([-t[1], t[0]]) / np.linalg.norm(t)
        images.append(NewImage(feats[i].codes, feats[i].keypoints, truth[i] + beside_m * left,
                               f"cloudy/{i}"))
    assert m.path is not None
    learned, _ = add_experience(m, m.path, "cloudy", images, condition="cloudy", robot=None,
                                now=1.0, budget_bytes=1 << 30)
    return learned


def _fixes(m: RouteMap, cloudy1: Round, feats: dict[int, Features]
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Per odd frame of the stretch located at the learned image nearest its true place:
    the learned image's fix alone, the fix at both layers, the truth; and the map's own
    images located beside (``extra``)."""
    loc = Localizer(m)
    layer = experience_layers(m)["cloudy"]
    alone, both, truth, extra = [], [], [], 0
    for i in FRAMES[1::2]:
        f = feats[i]
        plain = loc.locator(f, FramePairs(GeometryParams().delta))
        assert plain is not None  # the map has the camera
        image = int(m.nearest_in_layer(cloudy1.reference_xy[i][None, :], layer)[0][0])
        at_both = BothLayers(m, plain, loc.estimator.spacing)
        a, b = plain(image), at_both(image)
        extra += at_both.extra
        if a is None or b is None:
            continue
        s = loc.estimator.spacing
        alone.append(located_position(m.positions, image, a.right_m, a.ahead_m, s))
        both.append(located_position(m.positions, image, b.right_m, b.ahead_m, s))
        truth.append(cloudy1.reference_xy[i])
    return np.array(alone), np.array(both), np.array(truth), extra


def test_a_fix_at_a_misplaced_learned_image_is_averaged_with_the_maps_own(
        camera_map: RouteMap, cloudy1: Round, tmp_path: Path) -> None:
    """Each learned image sits 1 m beside its frame's true place: located at it alone the
    frames are about 1 m off; located at both layers (the map's own image of the place,
    sunny, carries no such error) they are about half as far off, and each learned fix cost
    one more map image located."""
    feats = {i: extract(cloudy1.load_image(i), camera_map.feature_params) for i in FRAMES}
    m = _learned(camera_map, cloudy1, feats, tmp_path, beside_m=1.0)
    alone, both, truth, extra = _fixes(m, cloudy1, feats)
    assert len(alone) >= 12  # most frames are located at their learned image
    assert extra >= len(alone)
    off_alone = np.linalg.norm(alone - truth, axis=1)
    off_both = np.linalg.norm(both - truth, axis=1)
    assert float(np.median(off_alone)) > 0.7  # the learned image's placement error
    assert float(np.median(off_both)) < 0.7 * float(np.median(off_alone))


def test_two_fixes_that_disagree_keep_the_learned_images(
        camera_map: RouteMap, cloudy1: Round, tmp_path: Path) -> None:
    """A learned image more than AGREE_M beside the map's own image of its place: the two
    fixes are two answers, and the learned image's fix is kept unchanged."""
    feats = {i: extract(cloudy1.load_image(i), camera_map.feature_params) for i in FRAMES}
    m = _learned(camera_map, cloudy1, feats, tmp_path, beside_m=AGREE_M + 2.0)
    alone, both, _, _ = _fixes(m, cloudy1, feats)
    assert len(alone) >= 5
    np.testing.assert_allclose(both, alone)
