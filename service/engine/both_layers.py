"""A frame located at an experience image is located at the map's own image of its place too.

On a map with experiences the particles at an experience's places are compared with its
images (``LayerChoice``, service/maps/experiences.py), so DPSO's two-view geometry locates a
tracked frame at a learned image (``MultiSwarmDPSO._located``). That fix carries the learned
image's position: where the learning robot was placed, 0.1-0.6 m from the truth on the
rendered worlds (docs/research/lighting.md, "Located at both layers"). The map's own image of
the same place carries an error of its own (its round's fix), and at dusk it locates the frame
about as well, with about as many RANSAC inliers (10-18 against 13-17: a dusk frame has few
features in either light); in cloudy light with fewer (14-28 against 73-92). So the frame is
located at both, and the fix is their mean: two fixes with independent errors average them.
Where the map's image does not locate the frame, or the two fixes lie more than ``AGREE_M``
apart (two answers, not one place), the learned image's fix is taken alone, as before. Each
such map image counts as one more comparison of the frame (``extra``; an upper bound: where
the frame's similarity already matched that image, the geometry reuses its matches).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from service.estimators.along_track import located_position, path_offset
from service.estimators.fitness import LocateFn
from service.maps.experiences import base_layers, nearest_base
from service.maps.route_map import RouteMap
from service.vision.metric_pose import Offset

AGREE_M = 3.0  # the two fixes of one place lie this close (metric_gate_m: a frame located
# farther from its image does not confirm the place)


@dataclass
class BothLayers:
    """One frame's ``locate`` on a map with experiences: at an experience image, the mean of
    its fix and the fix at the map's own image nearest to it."""

    m: RouteMap
    locate: LocateFn
    spacing: float  # the map's path scale (``Estimator.spacing``: its tangents' reach)
    own: np.ndarray  # per map image: one of the map's own (a base layer), not learned
    extra: int = 0  # the map's own images located beside a learned one (each matched once)

    def __call__(self, image_id: int) -> Offset | None:
        off = self.locate(image_id)
        if off is None or self.own[image_id]:
            return off
        positions = self.m.positions
        here = located_position(positions, image_id, off.right_m, off.ahead_m, self.spacing)
        ids, dist = nearest_base(self.m, positions[image_id][None, :], base_layers(self.m))
        own = int(ids[0, int(np.argmin(dist[0]))])
        self.extra += 1
        off_own = self.locate(own)
        there = None if off_own is None else \
            located_position(positions, own, off_own.right_m, off_own.ahead_m, self.spacing)
        if here is None or there is None or float(np.linalg.norm(there - here)) > AGREE_M:
            return off
        mean = path_offset(positions, image_id, (here + there) / 2, self.spacing)
        return off if mean is None else replace(off, right_m=mean[0], ahead_m=mean[1])
