"""Sequence matching along the wheels for a searching swarm (SeqSLAM, Milford & Wyeth 2012).

One frame at dusk says little: a wrong place often matches it as well as the true one, and a
searching swarm that follows the best match of each frame jumps between look-alikes tens of
metres apart. A *sequence* of frames says much more, where the robot's odometry tells how
far apart they were taken: the true place matches frame after frame, a look-alike only now
and then.

``PlaceSequence`` keeps hypotheses of where the robot is while its swarm searches. Each is a
place on the map's path and a direction along it; it is born at one of the frame's place
candidates (service/vision/place_index.py), in both directions, and moves with every frame
along the path by the distance the wheels travelled. Each frame it is scored like a
particle (journal Eq. 3 at its place), and it keeps the decayed mean of its scores. The
sequence's place is the hypothesis whose mean is at least ``ratio`` times that of every
other hypothesis FAR_M or more away, once it has seen ``min_frames`` frames over at least
``min_travel_m`` of travel (a robot standing still repeats one frame: no sequence).

Pure computation on arrays; the estimator owns it and decides what the place is used for
(service/estimators/multi_swarm_dpso.py).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from service.estimators.along_track import path_tangents

# scores of hypothesis positions: (n, 2) -> (n,)
ScoreFn = Callable[[np.ndarray], np.ndarray]
NearestIds = Callable[[np.ndarray], np.ndarray]  # positions (n, 2) -> nearest image ids (n,)

DECAY = 0.93  # weight of a hypothesis's previous mean per frame (a memory of ~14 frames)
MERGE_M = 1.0  # hypotheses of one direction closer than this are one
MAX_HYPOTHESES = 60  # kept at most, the best by their mean
FAR_M = 15.0  # a rival hypothesis lies at least this far away


class PlaceSequence:
    """Hypotheses (place, direction along the path, decayed mean score) of a searching
    swarm."""

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        self.x = np.zeros((0, 2))  # places on the path
        self.direction = np.zeros((0, 2))  # unit directions along it
        self.num = np.zeros(0)  # decayed sums of the scores
        self.den = np.zeros(0)  # decayed frame counts
        self.frames = np.zeros(0, np.int64)  # frames seen
        self.travel = np.zeros(0)  # metres moved since birth

    def __len__(self) -> int:
        return len(self.x)

    def step(self, distance: float, candidates: np.ndarray | None, positions: np.ndarray,
             spacing: float, nearest: NearestIds, score: ScoreFn) -> None:
        """One frame: move every hypothesis ``distance`` metres along the path of the map
        images ``positions`` (``nearest`` names the image nearest to a place; a negative
        distance, a robot backing up, moves it against its direction), add hypotheses at
        ``candidates`` (k, 2), then score them all with ``score``."""
        if len(self.x) and distance != 0:
            self._advance(distance, positions, spacing, nearest)
        if candidates is not None and len(candidates):
            self._add(np.asarray(candidates, float), positions, spacing, nearest)
        if not len(self.x):
            return
        self.num = DECAY * self.num + np.asarray(score(self.x), float)
        self.den = DECAY * self.den + 1.0
        self.frames = self.frames + 1
        self._merge()

    def place(self, min_frames: int, ratio: float, min_travel_m: float) -> np.ndarray | None:
        """The sequence's place (2,): the hypothesis with the best mean among those that
        have seen ``min_frames`` frames, where the wheels moved it ``min_travel_m`` or more
        and its mean is at least ``ratio`` times every other such hypothesis's FAR_M or more
        away; None while none stands out."""
        if not len(self.x):
            return None
        mean = self.num / np.maximum(self.den, 1e-12)
        mature = self.frames >= min_frames
        if not mature.any():
            return None
        best = int(np.argmax(np.where(mature, mean, -np.inf)))
        if self.travel[best] < min_travel_m:
            return None
        rivals = mature & (np.linalg.norm(self.x - self.x[best], axis=1) >= FAR_M)
        if not rivals.any() or mean[best] < ratio * float(mean[rivals].max()):
            return None
        return self.x[best].copy()

    def _on_path(self, at: np.ndarray, positions: np.ndarray, spacing: float,
                 nearest: NearestIds) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(``at`` moved onto the path: along the line of its nearest image; the path's
        unit direction there; whether it has one). A point whose image has no direction
        stays where it is, with a zero direction."""
        ids = np.asarray(nearest(at), np.int64)
        t = path_tangents(positions, ids, spacing)
        has = np.any(t != 0, axis=1)
        along = np.einsum("ij,ij->i", at - positions[ids], t)
        on_path = np.where(has[:, None], positions[ids] + along[:, None] * t, at)
        return on_path, t, has

    def _advance(self, distance: float, positions: np.ndarray, spacing: float,
                 nearest: NearestIds) -> None:
        _, t, has = self._on_path(self.x, positions, spacing, nearest)
        # the path's direction there, turned to the hypothesis's own
        t = np.where((np.einsum("ij,ij->i", t, self.direction) < 0)[:, None], -t, t)
        self.direction = np.where(has[:, None], t, self.direction)
        self.x, _, _ = self._on_path(self.x + distance * self.direction, positions, spacing,
                                     nearest)
        self.travel = self.travel + abs(distance)

    def _add(self, candidates: np.ndarray, positions: np.ndarray, spacing: float,
             nearest: NearestIds) -> None:
        at, t, keep = self._on_path(candidates, positions, spacing, nearest)
        at, t = at[keep], t[keep]
        x = np.concatenate([at, at])
        d = np.concatenate([t, -t])
        # not where a hypothesis of that direction already is (``_merge`` would drop it
        # after scoring it: this saves its comparison)
        if len(self.x):
            dist = np.linalg.norm(x[:, None, :] - self.x[None, :, :], axis=2)
            same = np.einsum("ik,jk->ij", d, self.direction) > 0
            new = ~((dist < MERGE_M) & same).any(axis=1)
            x, d = x[new], d[new]
        n = len(x)
        self.x = np.concatenate([self.x, x])
        self.direction = np.concatenate([self.direction, d])
        self.num = np.concatenate([self.num, np.zeros(n)])
        self.den = np.concatenate([self.den, np.zeros(n)])
        self.frames = np.concatenate([self.frames, np.zeros(n, np.int64)])
        self.travel = np.concatenate([self.travel, np.zeros(n)])

    def _merge(self) -> None:
        """Hypotheses that met (one direction, within MERGE_M) become the one that has seen
        most frames (then the better); at most MAX_HYPOTHESES are kept, the best means."""
        mean = self.num / np.maximum(self.den, 1e-12)
        order = np.lexsort((-mean, -self.frames))
        dist = np.linalg.norm(self.x[:, None, :] - self.x[None, :, :], axis=2)
        same = (dist < MERGE_M) & (np.einsum("ik,jk->ij", self.direction,
                                             self.direction) > 0)
        keep = np.zeros(len(self.x), bool)
        gone = np.zeros(len(self.x), bool)
        for i in order:
            if gone[i]:
                continue
            keep[i] = True
            gone |= same[i]
        idx = np.flatnonzero(keep)
        if len(idx) > MAX_HYPOTHESES:
            idx = idx[np.argsort(-mean[idx], kind="stable")[:MAX_HYPOTHESES]]
            idx.sort()
        for name in ("x", "direction", "num", "den", "frames", "travel"):
            setattr(self, name, getattr(self, name)[idx])
