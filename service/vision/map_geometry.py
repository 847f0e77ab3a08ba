"""A map's two-view geometry: the structure of its images, kept, and a frame located at one.

``MapGeometry.locate(features, i)`` answers where the frame's camera stands relative to map
image ``i`` (service/vision/metric_pose.py). The structure of ``i`` (its features' 3-D points)
comes from the neighbours of its traversal ahead and behind (``views_m``): each pair's pose
from its essential matrix, computed once for both of its images, and each point triangulated
from every neighbour that holds it, where at least ``min_views`` do; where they give too few
points, from the partner ``baseline_m`` away alone. It depends on the map alone, so it is
computed once per image and kept, bounded, for every session on the map. The frame's own
matches with ``i`` come from its similarity's pass where that kept them (``FramePairs``), so
locating the frame matches nothing again.

The located frame's heading in the map is the map image camera's heading plus the frame's
yaw relative to it (PnP's rotation). The map keeps positions, not headings. Its cameras look
along their traversal on the whole, but each turns a few degrees about the path (a robot's
wobble), which positions cannot tell; the pairs' rotations can (the structure's partner
yaw: a fraction of a degree). So a map image's heading is a circular mean over a chain of
partners, ``heading_hops`` beyond the image: at each link, the traversal's direction
there (the principal axis of its positions within ``heading_window_m``, oriented in the
order the images were taken) less the link's yaw relative to the image, the partners' yaws
summed. The wobble averages out over the chain and the positions' noise over each window
(a neighbour one image away gives 6° median error with 0.3 m GPS noise; docs/research/
odometry.md has the measured errors).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass, replace
from typing import Protocol

import cv2
import numpy as np

from service.api.geo import wrap_angle
from service.vision.features import Features
from service.vision.matcher import Pairs
from service.vision.metric_pose import (
    Camera,
    Offset,
    PairPose,
    Structure,
    locate,
    relative_pose,
    relative_yaw,
    triangulate,
    triangulate_views,
)

# std (rad) of a located frame's heading, 2.9°: near the spread measured on the located,
# tracked frames of the rendered worlds (median 2.19°, p90 5.2°; docs/research/odometry.md)
LOCATED_HEADING_SIGMA = 0.05
POSES_KEPT = 1024  # neighbouring pairs' poses kept: those of the structures built lately


class _Images(Protocol):  # what this module needs of a RouteMap (service/maps/route_map.py)
    positions: np.ndarray
    layers: np.ndarray | None

    def codes_of(self, image_id: int) -> np.ndarray: ...

    def keypoints_of(self, image_id: int) -> np.ndarray: ...

    def pairs(self, codes: np.ndarray, image_id: int, delta: float
              ) -> tuple[np.ndarray, np.ndarray]: ...

    def image_pairs(self, image_id: int, other: int, delta: float
                    ) -> tuple[np.ndarray, np.ndarray]: ...


@dataclass(frozen=True)
class GeometryParams:
    """How a frame is located at a map image."""

    delta: float = 0.9  # ratio threshold of the matches used for geometry (looser than m's)
    min_inliers: int = 8  # RANSAC inliers needed, for the structure and for the frame
    baseline_m: float = 2.4  # the partner: the neighbour that gives an image's structure
    # with two views, and the next link of its heading's chain; with ``views_m``, the
    # neighbours ahead and behind at each of these distances give it, a point where
    # ``min_views`` of them see it
    views_m: tuple[float, ...] = (1.2, 2.4)
    min_views: int = 2  # 0: two views, the partner's alone
    heading_window_m: float = 6.0  # reach of the path's direction at a map image, each way
    heading_hops: int = 3  # partners beyond a map image whose directions its heading averages


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
        self._headings: OrderedDict[tuple[int, GeometryParams], float | None] = OrderedDict()
        # the poses of neighbouring pairs, each computed once for both of its images' structures
        self._poses: OrderedDict[tuple[int, int, GeometryParams], PairPose | None] = \
            OrderedDict()
        self._lock = threading.Lock()

    def _along(self, image_id: int, step: int, distance_m: float) -> int | None:
        """The image of ``image_id``'s traversal nearest to ``distance_m`` away along the id
        order in direction ``step`` (1: ahead, -1: behind), between half and twice that
        distance; None if none."""
        pos = self.images.positions
        layers = self.images.layers
        here = pos[image_id]
        j, best, best_gap = image_id + step, None, np.inf
        while 0 <= j < len(pos) and (layers is None or layers[j] == layers[image_id]):
            d = float(np.linalg.norm(pos[j] - here))
            if d > 2.0 * distance_m:
                break
            if d >= 0.5 * distance_m and abs(d - distance_m) < best_gap:
                best, best_gap = j, abs(d - distance_m)
            j += step
        return best

    def partner(self, image_id: int, baseline_m: float) -> int | None:
        """The image of ``image_id``'s traversal nearest to ``baseline_m`` away along the id
        order (ahead, else behind), between half and twice that distance; None if none."""
        ahead = self._along(image_id, 1, baseline_m)
        return ahead if ahead is not None else self._along(image_id, -1, baseline_m)

    def neighbours(self, image_id: int, p: GeometryParams) -> list[int]:
        """The images whose poses give ``image_id``'s structure: with ``p.min_views``, those
        of its traversal nearest to each of ``p.views_m`` ahead and behind; else its partner."""
        if p.min_views <= 0:
            j = self.partner(image_id, p.baseline_m)
            return [] if j is None else [j]
        out: list[int] = []
        for d in p.views_m:
            for step in (1, -1):
                j = self._along(image_id, step, d)
                if j is not None and j not in out:
                    out.append(j)
        return out

    def pair_pose(self, i: int, j: int, p: GeometryParams) -> PairPose | None:
        """The pose of map image ``j`` seen from image ``i`` (``relative_pose``), computed
        once per pair in id order and kept, bounded."""
        a, b = min(i, j), max(i, j)
        key = (a, b, p)
        with self._lock:
            hit = key in self._poses
            pose = self._poses.get(key)
            if hit:
                self._poses.move_to_end(key)
        if not hit:
            pos = self.images.positions
            try:
                pose = relative_pose(self.images.keypoints_of(a), self.images.keypoints_of(b),
                                     self.images.image_pairs(a, b, p.delta),
                                     float(np.linalg.norm(pos[b] - pos[a])), self.k,
                                     p.min_inliers)
            except cv2.error:  # a degenerate configuration: no pose
                pose = None
            with self._lock:
                self._poses[key] = pose
                while len(self._poses) > POSES_KEPT:
                    self._poses.popitem(last=False)
        if pose is None or i == a:
            return pose
        return pose.inverse()

    def path_heading(self, image_id: int, window_m: float) -> float | None:
        """Direction (rad counter-clockwise from east) of ``image_id``'s traversal there: the
        principal axis of the traversal's positions within ``window_m`` of the image, along
        the id order; None where no other image of the traversal lies that near."""
        pos = self.images.positions
        layers = self.images.layers
        here = pos[image_id]
        ends = []
        for step in (-1, 1):
            j = image_id
            while 0 <= j + step < len(pos) and \
                    (layers is None or layers[j + step] == layers[image_id]) and \
                    float(np.linalg.norm(pos[j + step] - here)) <= window_m:
                j += step
            ends.append(j)
        lo, hi = ends
        if hi == lo:
            return None
        near = np.asarray(pos[lo:hi + 1], float)
        axis = np.linalg.svd(near - near.mean(axis=0), full_matrices=False)[2][0]
        if float(axis @ (near[-1] - near[0])) < 0:
            axis = -axis
        return float(np.arctan2(axis[1], axis[0]))

    def camera_heading(self, image_id: int, p: GeometryParams) -> float | None:
        """The heading (rad counter-clockwise from east) of map image ``image_id``'s camera:
        the circular mean, over the image and ``heading_hops`` partners beyond it, of the
        traversal's direction at each less its yaw relative to the image; None where the
        traversal's direction is not known there."""
        key = (int(image_id), p)
        with self._lock:
            if key in self._headings:
                self._headings.move_to_end(key)
                return self._headings[key]
        chain, turned, votes = self._chain(image_id, p), 0.0, []
        for k, image in enumerate(chain):
            direction = self.path_heading(image, p.heading_window_m)
            if direction is not None:
                votes.append(direction - turned)
            pose = self.pair_pose(image, chain[k + 1], p) if k + 1 < len(chain) else None
            if pose is None:
                break
            turned += relative_yaw(pose.rot)
        heading = float(np.angle(np.exp(1j * np.asarray(votes)).sum())) if votes else None
        with self._lock:
            self._headings[key] = heading
            while len(self._headings) > self.max_cached:
                self._headings.popitem(last=False)
        return heading

    def structure(self, image_id: int, p: GeometryParams) -> Structure | None:
        """Image ``image_id``'s features' 3-D points (``triangulate_views`` over its
        ``neighbours``; where they give too few, ``triangulate`` with its partner alone),
        computed once and kept, bounded."""
        key = (int(image_id), p)
        with self._lock:
            if key in self._cache:
                self._cache.move_to_end(key)
                return self._cache[key]
        j = self.partner(image_id, p.baseline_m)
        st = self._views(int(image_id), p) if p.min_views > 0 else None
        if st is None and j is not None:
            baseline = float(np.linalg.norm(self.images.positions[j]
                                             - self.images.positions[image_id]))
            pairs = self.images.image_pairs(image_id, j, p.delta)
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

    def _views(self, i: int, p: GeometryParams) -> Structure | None:
        views = []
        for j in self.neighbours(i, p):
            pose = self.pair_pose(i, j, p)
            if pose is not None:
                views.append((pose, self.images.keypoints_of(j)))
        try:
            return triangulate_views(self.images.keypoints_of(i), views, self.k, p.min_views,
                                     p.min_inliers)
        except np.linalg.LinAlgError:  # SVD did not converge: no structure from these views
            return None

    def carry(self, old: MapGeometry, ids: np.ndarray) -> int:
        """Keep the structures and camera headings ``old`` (the geometry of another version of
        the same map, the same camera) has built, for the images this version holds
        unchanged: ``ids[i]`` is this version's id of ``old``'s image ``i`` (-1: not here). A
        structure is carried where its image's partner and neighbours are the same images in
        both versions (a new image of the same traversal can be the nearer one now); a
        heading where its chain of partners is, with the same traversal's direction at each
        (``path_heading``); returns how many structures were. The robots on the new version
        then find them built, as on the old one."""
        if not np.array_equal(old.k, self.k):
            return 0
        with old._lock:
            items = list(old._cache.items())
            headings = list(old._headings.items())

        def here(i: int) -> int:
            return int(ids[i]) if 0 <= i < len(ids) else -1

        n = 0
        for (i, p), st in items:
            j = here(i)
            if j < 0:
                continue
            was = [old.partner(i, p.baseline_m), *old.neighbours(i, p)]
            now = [self.partner(j, p.baseline_m), *self.neighbours(j, p)]
            if [None if w is None else here(w) for w in was] != now:
                continue
            with self._lock:
                self._cache.setdefault((j, p), st)
                while len(self._cache) > self.max_cached:
                    self._cache.popitem(last=False)
            n += 1
        directions: dict[tuple[bool, int, float], float | None] = {}  # path_heading, once each

        def direction(g: MapGeometry, i: int, window_m: float) -> float | None:
            key = (g is old, i, window_m)
            if key not in directions:
                directions[key] = g.path_heading(i, window_m)
            return directions[key]

        for (i, p), heading in headings:
            j = here(i)
            if j < 0:
                continue
            chain_was, chain_now = old._chain(i, p), self._chain(j, p)
            if [here(w) for w in chain_was] != chain_now or \
                    [direction(old, w, p.heading_window_m) for w in chain_was] != \
                    [direction(self, w, p.heading_window_m) for w in chain_now]:
                continue
            with self._lock:
                self._headings.setdefault((j, p), heading)
                while len(self._headings) > self.max_cached:
                    self._headings.popitem(last=False)
        return n

    def _chain(self, image_id: int, p: GeometryParams) -> list[int]:
        """The images whose traversal's direction and pair rotations ``camera_heading``
        reads: ``image_id`` and up to ``heading_hops`` partners beyond it."""
        chain = [int(image_id)]
        while len(chain) <= p.heading_hops:
            j = self.partner(chain[-1], p.baseline_m)
            if j is None or j in chain:
                break
            chain.append(j)
        return chain

    def cached(self) -> list[int]:
        """The images whose structure (or its absence) is kept now, at any parameters."""
        with self._lock:
            return sorted({i for i, _ in self._cache})

    def warm(self, image_ids: Iterable[int] | None = None, p: GeometryParams | None = None
             ) -> int:
        """Compute and keep the structures and headings of ``image_ids`` (``ready``; default:
        every image, up to the cache's bound) ahead of the frames that need them; returns how
        many images have a structure. They depend on the map alone: the same a frame would
        compute."""
        p = GeometryParams() if p is None else p
        ids = range(min(len(self.images.positions), self.max_cached)) if image_ids is None \
            else image_ids
        return sum(self.ready(int(i), p) is not None for i in ids)

    def ready(self, image_id: int, p: GeometryParams) -> Structure | None:
        """Build and keep what locating a frame at ``image_id`` needs: its structure and, where
        it has one, its camera's heading. The heading reads pair poses along a chain of
        partners, and only ``POSES_KEPT`` poses are kept: on a map of more pairs than that, a
        heading left for the frame would build again the poses its warming already built."""
        st = self.structure(image_id, p)
        if st is not None:
            self.camera_heading(image_id, p)
        return st

    def locate(self, frame: Features, image_id: int, p: GeometryParams,
               kept: FramePairs | None = None) -> Offset | None:
        """The frame's camera centre relative to map image ``image_id``'s camera (metres
        right, ahead), its yaw relative to it and its heading in the map; None where the
        geometry is not reliable. ``kept``: this frame's matches kept by its similarity
        (matched here where it has none for the image)."""
        st = self.structure(image_id, p)
        if st is None:
            return None
        pairs = kept.get(image_id) if kept is not None and kept.delta == p.delta else None
        if pairs is None:
            pairs = self.images.pairs(frame.codes, image_id, p.delta)
        try:
            off = locate(frame.keypoints, pairs, st, self.k, p.min_inliers)
        except cv2.error:  # a degenerate configuration: the frame is not located
            return None
        base = self.camera_heading(image_id, p) if off is not None else None
        if off is None or base is None:
            return off
        heading = wrap_angle(base + off.yaw)
        return replace(off, heading=heading, heading_sigma=LOCATED_HEADING_SIGMA)
