"""A map's two-view geometry: the structure of its images, kept, and a frame located at one.

``MapGeometry.locate(features, i)`` answers where the frame's camera stands relative to map
image ``i`` (service/vision/metric_pose.py). The structure of ``i`` (its features' 3-D points, from
``i`` and a neighbour of its traversal ``baseline_m`` away) depends on the map alone, so it is
computed once per image and kept, bounded, for every session on the map. The frame's own
matches with ``i`` come from its similarity's pass where that kept them (``FramePairs``), so
locating the frame matches nothing again.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np

from service.vision.features import Features
from service.vision.matcher import Pairs
from service.vision.metric_pose import Camera, Offset, Structure, locate, triangulate


class _Images(Protocol):  # what this module needs of a RouteMap (service/maps/route_map.py)
    positions: np.ndarray
    layers: np.ndarray | None

    def codes_of(self, image_id: int) -> np.ndarray: ...

    def keypoints_of(self, image_id: int) -> np.ndarray: ...

    def pairs(self, codes: np.ndarray, image_id: int, delta: float
              ) -> tuple[np.ndarray, np.ndarray]: ...


@dataclass(frozen=True)
class GeometryParams:
    """How a frame is located at a map image."""

    delta: float = 0.9  # ratio threshold of the matches used for geometry (looser than m's)
    min_inliers: int = 8  # RANSAC inliers needed, for the structure and for the frame
    baseline_m: float = 2.4  # distance to the neighbour that gives an image its structure


class FramePairs:
    """One frame's matches at ``delta`` with the map images its similarity compared, kept by
    the similarity's own pass (``RouteMap.similarity(..., keep=)``): the two-view geometry
    locates the frame at one of them without matching it again (the same pairs, bit for
    bit: one GEMM and scan decided at two ratio thresholds)."""

    def __init__(self, delta: float) -> None:
        self.delta = delta
        self._pairs: dict[int, Pairs] = {}

    def keep(self, image_ids: list[int], pairs: list[Pairs]) -> None:
        self._pairs.update(zip(image_ids, pairs, strict=True))

    def get(self, image_id: int) -> Pairs | None:
        return self._pairs.get(int(image_id))


class MapGeometry:
    """The geometry of one map with camera ``camera``; thread-safe, bounded cache."""

    def __init__(self, images: _Images, camera: Camera, width: int, height: int,
                 max_cached: int = 4096) -> None:
        self.images = images
        self.k = camera.matrix(width, height)
        self.max_cached = max_cached
        self._cache: OrderedDict[tuple[int, GeometryParams], Structure | None] = OrderedDict()
        self._lock = threading.Lock()

    def partner(self, image_id: int, baseline_m: float) -> int | None:
        """The image of ``image_id``'s traversal nearest to ``baseline_m`` away along the id
        order (ahead, else behind), between half and twice that distance; None if none."""
        pos = self.images.positions
        layers = self.images.layers
        here = pos[image_id]
        for step in (1, -1):
            j, best, best_gap = image_id + step, None, np.inf
            while 0 <= j < len(pos) and (layers is None or layers[j] == layers[image_id]):
                d = float(np.linalg.norm(pos[j] - here))
                if d > 2.0 * baseline_m:
                    break
                if d >= 0.5 * baseline_m and abs(d - baseline_m) < best_gap:
                    best, best_gap = j, abs(d - baseline_m)
                j += step
            if best is not None:
                return best
        return None

    def structure(self, image_id: int, p: GeometryParams) -> Structure | None:
        key = (int(image_id), p)
        with self._lock:
            if key in self._cache:
                self._cache.move_to_end(key)
                return self._cache[key]
        j = self.partner(image_id, p.baseline_m)
        st = None
        if j is not None:
            baseline = float(np.linalg.norm(self.images.positions[j]
                                             - self.images.positions[image_id]))
            pairs = self.images.pairs(self.images.codes_of(image_id), j, p.delta)
            try:
                st = triangulate(self.images.keypoints_of(image_id),
                                 self.images.keypoints_of(j), pairs, baseline, self.k,
                                 p.min_inliers)
            except cv2.error:  # a degenerate configuration: no structure, not a failed frame
                st = None
        with self._lock:
            self._cache[key] = st
            while len(self._cache) > self.max_cached:
                self._cache.popitem(last=False)
        return st

    def warm(self, image_ids: Iterable[int] | None = None, p: GeometryParams | None = None
             ) -> int:
        """Compute and keep the structures of ``image_ids`` (default: every image, up to the
        cache's bound) ahead of the frames that need them; returns how many images have one.
        They depend on the map alone: the same structures a frame would compute."""
        p = GeometryParams() if p is None else p
        ids = range(min(len(self.images.positions), self.max_cached)) if image_ids is None \
            else image_ids
        return sum(self.structure(int(i), p) is not None for i in ids)

    def locate(self, frame: Features, image_id: int, p: GeometryParams,
               kept: FramePairs | None = None) -> Offset | None:
        """The frame's camera centre relative to map image ``image_id``'s camera (metres
        right, ahead); None where the geometry is not reliable. ``kept``: this frame's matches
        kept by its similarity (matched here where it has none for the image)."""
        st = self.structure(image_id, p)
        if st is None:
            return None
        pairs = kept.get(image_id) if kept is not None and kept.delta == p.delta else None
        if pairs is None:
            pairs = self.images.pairs(frame.codes, image_id, p.delta)
        try:
            return locate(frame.keypoints, pairs, st, self.k, p.min_inliers)
        except cv2.error:  # a degenerate configuration: the frame is not located
            return None
