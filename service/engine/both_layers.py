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

from service.estimators.along_track import along_path, located_position, path_tangent
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
    extra: int = 0  # the map's own images located beside a learned one (each matched once)

    def __post_init__(self) -> None:
        self._base = base_layers(self.m)  # the map's own layers (its traversals)

    def __call__(self, image_id: int) -> Offset | None:
        off = self.locate(image_id)
        layers = self.m.layers
        if off is None or layers is None or int(layers[image_id]) in self._base:
            return off
        positions = self.m.positions
        ids, dist = nearest_base(self.m, positions[image_id][None, :], self._base)
        own = int(ids[0, int(np.argmin(dist[0]))])
        self.extra += 1
        off_own = self.locate(own)
        tangent = path_tangent(positions, image_id, self.spacing)
        there = None if off_own is None else \
            located_position(positions, own, off_own.right_m, off_own.ahead_m, self.spacing)
        if tangent is None or there is None:
            return off
        here = along_path(positions[image_id], tangent, off.right_m, off.ahead_m)
        if float(np.linalg.norm(there - here)) > AGREE_M:
            return off
        d = (here + there) / 2 - positions[image_id]  # the mean, as an offset from the image
        return replace(off, right_m=float(d @ np.array([tangent[1], -tangent[0]])),
                       ahead_m=float(d @ tangent))
