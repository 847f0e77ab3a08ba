"""Fitness of particle positions for one frame (journal Eq. 3).

    f(x, t) = m(i_M(x), s(t)) * zeta(dist(x, p_M(i_M(x))))

i_M(x) is the map image nearest to x, m the image similarity and zeta a Gaussian penalty of the
distance to that image's position. Particles sharing a nearest image share one comparison; the
number of distinct images compared in a frame is the papers' "comparisons per image". In a map
merged from several traversals (layers), a particle is compared with the nearest image of each
layer and keeps the best m * zeta; every image compared counts. A map with experiences gives
a ``nearest`` that picks the layers of this frame instead (service/maps/experiences.py).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from service.vision.metric_pose import Offset

SimilarityFn = Callable[[np.ndarray], np.ndarray]  # map image ids -> m(frame, image)
# map image id -> the frame's camera relative to that image's (service/vision/metric_pose.py)
LocateFn = Callable[[int], "Offset | None"]
# particle positions -> (ids, distances), each (n, k): the map images each particle is compared
# with (a map with experiences: the layer chosen for this frame, service/maps/experiences.py)
NearestFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


class MapIndex(Protocol):
    """What an estimator sees of a map: image positions and a nearest-image query."""

    positions: np.ndarray

    def nearest(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

    def nearest_per_layer(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


class ComparisonCache:
    """A frame's similarity that compares each map image once, and counts them: the
    papers' comparisons per image. Called like the similarity it wraps."""

    def __init__(self, similarity: SimilarityFn) -> None:
        self._similarity = similarity
        self._ids = np.zeros(0, np.int64)
        self._scores = np.zeros(0)

    @property
    def comparisons(self) -> int:
        """Distinct map images compared for this frame so far."""
        return len(self._ids)

    def __call__(self, ids: np.ndarray) -> np.ndarray:
        return self.scores_of(ids)

    def scores_of(self, ids: np.ndarray) -> np.ndarray:
        """m(frame, image) for map image ids, comparing each distinct new id once."""
        uniq, inv = np.unique(ids, return_inverse=True)
        new = np.setdiff1d(uniq, self._ids, assume_unique=True)
        if len(new):
            self._ids = np.concatenate([self._ids, new])
            self._scores = np.concatenate([self._scores, self._similarity(new)])
            order = np.argsort(self._ids)
            self._ids, self._scores = self._ids[order], self._scores[order]
        return self._scores[np.searchsorted(self._ids, uniq)][inv].reshape(np.shape(ids))

    @property
    def compared(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids, m) of every map image compared in this frame so far."""
        return self._ids, self._scores


class TypeScores:
    """The first feature type's own m of the map images a frame was compared with, on a map
    of two types (recorded by the similarity beside the fused m it returns; read by the lost
    detection, service/estimators/lost_detection.py). Called with ids like a similarity;
    an image not compared has NaN."""

    def __init__(self) -> None:
        self._m: dict[int, float] = {}

    def record(self, ids: np.ndarray, m: np.ndarray) -> None:
        self._m.update(zip((int(i) for i in ids), (float(v) for v in m), strict=True))

    def __call__(self, ids: np.ndarray) -> np.ndarray:
        return np.array([self._m.get(int(i), np.nan) for i in np.ravel(ids)]).reshape(
            np.shape(ids))


class FrameFitness:
    """Eq. 3 for one frame, with a per-frame comparison cache and counter."""

    def __init__(self, index: MapIndex, similarity: SimilarityFn, penalty_sigma_m: float,
                 locate: LocateFn | None = None, nearest: NearestFn | None = None,
                 first: SimilarityFn | None = None) -> None:
        self._index = index
        self._nearest = nearest or index.nearest_per_layer
        self._cache = ComparisonCache(similarity)
        self.locate = locate  # None: the frame can only be placed at map images
        # the first feature type's own m (a map of two types: ``TypeScores``), else None
        self.first = first
        self._inv_two_sigma2 = 1.0 / (2.0 * penalty_sigma_m**2)

    @property
    def comparisons(self) -> int:
        """Distinct map images compared for this frame so far."""
        return self._cache.comparisons

    def scores_of(self, ids: np.ndarray) -> np.ndarray:
        """m(frame, image) for map image ids, comparing each distinct new id once."""
        return self._cache.scores_of(ids)

    @property
    def compared(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids, m) of every map image compared in this frame so far."""
        return self._cache.compared

    def __call__(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(fitness, similarity m, nearest image id) for each particle position."""
        ids, dist = self._nearest(positions)  # (n, layers)
        m = self.scores_of(ids)
        f = m * np.exp(-(dist**2) * self._inv_two_sigma2)
        k = np.argmax(f, axis=1)[:, None]
        return (np.take_along_axis(f, k, 1)[:, 0], np.take_along_axis(m, k, 1)[:, 0],
                np.take_along_axis(ids, k, 1)[:, 0])
