"""Learning sessions: frames where a robot is confidently localized become an experience.

A session created with ``learn`` hands each estimate to ``Learner.submit``, which runs
``Learner.observe`` on the learner's own threads (service/engine/learn_queue.py: the frame
is answered before its gates run, a robot's frames in the order they came). A frame teaches
only when every gate holds (a kidnapped or lost robot never does), or when the robot's wheels
bridge it between two frames that did (below):

1. the estimate is ``tracking`` with ``accuracy_m`` at most ``learn_accuracy_m`` or, where it
   is tracking with a larger ``accuracy_m``, gate 4 locates it (the learner's own two-view
   geometry confirms the estimate within ``LOCATED_TOLERANCE_M``);
2. it agrees with the recent path: the two frames before were tracked estimates of the same
   session, and the constant-velocity prediction from them lies within ``PATH_TOLERANCE_M``;
3. the map's layers match it weakly there: the best similarity of the nearest image of every
   layer near the estimate is below ``learn_weak_ratio`` of the map's same-light level (the
   median similarity of its consecutive images, ``same_light_level``), so the frame adds a
   new appearance;
4. where the map has the camera, two-view geometry locates the frame at one of those images,
   within ``LOCATED_TOLERANCE_M`` of the estimate (on a map of two feature types with either
   type's matches); the located position is the image's position in the experience (the
   estimate where the map has no camera).

The taught frames' positions are then placed together (``placed``): where the robot sent its
wheel odometry with every one of them, the odometry's path aligned to their located positions
over a window of travel, as a map's positions are fused with its round's odometry
(service/maps/positions.py; the previous batch's taught frames join the alignment); else a
line through the located positions of nearby frames.

Frames between two taught ones are *bridged by the wheels*: where the robot sends its
odometry, a frame stopped by gate 1, 2 or 4 after a taught frame is held, and when the next
frame is taught within ``BRIDGE_M`` of travel, and the wheels agree with where it was located
(``wheels_agree``: their step from the frame before the stretch, turned into the map by that
frame's located camera heading, and their path aligned to the taught frames before, put it
within ``BRIDGE_TOLERANCE_M``, so a robot carried off between them, along its way or across
it, is not bridged), the held frames join the collection if they pass gates 3 and 5 at the
place the wheels give them; ``placed`` then places them by the odometry alone, aligned to the
taught frames around them. The frames held before a session's first taught frame (its start,
while the swarm searched: its *lead*, up to ``BRIDGE_M`` of travel back) are taught by the
wheels too, back from that frame as far as each step of the lead is one the wheels made
(``LeadSteps.follows``: the images' step between two frames, scaled by the wheels' step before it,
within a factor ``LEAD_RATIO`` of the wheels' own; a robot carried in the lead, unseen by its
wheels, breaks it there): the wheels' step back from the taught frame, turned into the map by
its located heading, places them for gates 3 and 5, and ``placed`` by the odometry aligned to
the taught frames after them. A reset drops the lead. A session that never tracks
confidently teaches no frame, so it bridges none either.

Taught frames are kept (one per place) until ``learn_commit_images`` are collected or the
session ends or is reset; then the map admin writes them into the map as a new version
(service/maps/experiences.py). The collected frames stay in this process's memory, not in the
stored session: a replica that dies loses at most one batch (and the frames waiting for their
gates), never a map. Gates 1 and 2 read only the session's recent path (``path_gate``), which
is kept with the stored session: a robot whose frames alternate between replicas (an HTTP
round robin on a shared store) keeps its path, each replica collects the frames it served
into the same experience (its id comes from the robot and the session's creation), and a
replica writes a collection its robot has left for ``idle_s`` (``flush_idle``).
"""

from __future__ import annotations

import hashlib
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from typing import TypeVar

import cv2
import numpy as np

from service.api.models import Estimate, Odometry
from service.engine.learn_queue import LearnQueue
from service.estimators.along_track import along_path, path_tangent
from service.maps.experiences import (
    GAP_SPACINGS,
    PLACE_SPACINGS,
    NewImage,
    Usage,
    base_identity,
    base_spacing,
    same_light_level,
)
from service.maps.positions import fuse_with_odometry
from service.maps.route_map import RouteMap
from service.vision.features import Features
from service.vision.map_geometry import GeometryParams
from service.vision.metric_pose import Structure, locate, triangulate

T = TypeVar("T")
PATH_TOLERANCE_M = 1.0  # the estimate lies this close to the path's constant-velocity prediction
LOCATED_TOLERANCE_M = 1.0  # and this close to where the geometry locates the frame
GEOMETRY_TRIES = 3  # images near the estimate the geometry tries, best match first
SMOOTH_FRAMES = 4  # learned positions: a line through the taught frames this many frames away
CONTEXT_FRAMES = 48  # the last batch's taught frames that place the next one's first frames
BRIDGE_M = 15.0  # a stretch between two taught frames this long (odometry) is taught by the wheels
BRIDGE_FRAMES = 64  # and holds at most this many frames
BRIDGE_TOLERANCE_M = 3.0  # the wheels put the frame after a stretch this close to where it was
# located (``wheels_agree``)
LEAD_RATIO = 2.0  # a lead's step seen by the images lies within this factor of the wheels'
LEAD_MIN_STEP_M = 0.1  # and both steps it is measured on are this long (the wheels')
PROGRESS_WAIT_S = 1.0  # a session's learning progress waits this long for its queued gates
# a learning frame's outcomes: taught, bridged by the wheels, or stopped by a gate
OUTCOMES = ("taught", "bridged", "confident", "path", "appearance", "located", "place")
LEARN_IDLE_S = 30.0  # a replica writes what it collected of a robot that sent it nothing so long

Context = list[tuple[int, np.ndarray, np.ndarray]]  # a batch's taught frames (seq, xy, odometry)
Held = tuple[NewImage, int, np.ndarray]  # a frame held for the wheels: (image, seq, odometry)
Commit = Callable[[str, str, list[NewImage], str | None, str, str | None], None]
# (map name, experience id, images, condition, robot id, the map's ``base_identity`` where
# they were learned) -> written (the map admin's)


@dataclass(frozen=True)
class LearnGates:
    accuracy_m: float
    weak_ratio: float
    commit_images: int


@dataclass
class _Trail:
    """One learning robot's collection on one map."""

    exp_id: str
    map_name: str
    condition: str | None
    base: str | None = None  # ``base_identity`` of the map its collection was learned on
    last_seen: float = 0.0  # when the robot's last frame here was observed (time.monotonic)
    pending: list[NewImage] = field(default_factory=list)
    taught: int = 0  # frames that passed the gates
    with_odometry: int = 0  # of them, sent with the robot's odometry
    seen: int = 0
    refused: dict[str, int] = field(default_factory=dict)  # frames stopped, by gate
    seqs: list[int] = field(default_factory=list)  # the frame number of each pending image
    odometry: list[np.ndarray | None] = field(default_factory=list)  # each one's (x, y), if sent
    known: list[bool] = field(default_factory=list)  # each one located (False: bridged)
    anchor: tuple[int, np.ndarray, np.ndarray] | None = None  # last taught (seq, xy, odometry)
    turn: float | None = None  # the anchor's located heading less its odometry yaw
    gap: list[Held] = field(default_factory=list)  # since it
    gap_m: float = 0.0  # the wheels' travel since it
    bridged: int = 0
    context: Context = field(default_factory=list)  # the last batch's taught frames
    lead: list[Held] = field(default_factory=list)  # held before the session's first taught
    # frame, oldest first

    def refuse(self, gate: str) -> None:
        self.refused[gate] = self.refused.get(gate, 0) + 1


def smoothed(images: list[NewImage], seqs: list[int], k: int = SMOOTH_FRAMES
             ) -> list[NewImage]:
    """The images with their positions on the least-squares line (in frame number) through
    the taught frames within ``k`` frames: along a run the robot moves steadily, and each
    located position's own error averages out."""
    s = np.asarray(seqs, float)
    xy = np.array([f.xy for f in images], float).reshape(-1, 2)
    out = []
    for i, f in enumerate(images):
        near = np.abs(s - s[i]) <= k
        if near.sum() < 3:
            out.append(f)
            continue
        a = np.column_stack([np.ones(int(near.sum())), s[near] - s[i]])
        coef, *_ = np.linalg.lstsq(a, xy[near], rcond=None)
        out.append(replace(f, xy=coef[0]))
    return out


def placed(images: list[NewImage], seqs: list[int], odometry: list[np.ndarray | None],
           known: list[bool] | None = None, context: Context | None = None
           ) -> list[NewImage]:
    """The taught images with their positions for the experience. Where the robot sent its
    odometry with each of them (three or more): its path aligned to their located positions
    over ``positions.WINDOW_M`` of travel on either side (``fuse_with_odometry``: the wheels
    keep the shape between frames, the located positions of a whole stretch place it, and
    each one's error averages out), unless it does not fit them (a reset odometry); else
    ``smoothed``. ``known``: which images were located (False: bridged by the wheels, placed
    by the alignment alone, and left out where there is no odometry to place them);
    ``context``: the previous batch's taught frames, which join the alignment (not the
    output)."""
    k = np.ones(len(images), bool) if known is None else np.asarray(known, bool)
    order = np.argsort(np.asarray(seqs), kind="stable")  # bridged frames join after the next
    images, seqs, k = [images[i] for i in order], [seqs[i] for i in order], k[order]
    if k.sum() >= 3 and len(odometry) == len(images) and \
            all(o is not None for o in odometry):
        odometry = [odometry[i] for i in order]
        ctx = [c for c in (context or []) if c[0] < seqs[0]]
        n = len(ctx)
        xy = np.array([c[1] for c in ctx] + [f.xy for f in images], float).reshape(-1, 2)
        odo = np.array([c[2] for c in ctx] + odometry, float).reshape(-1, 2)
        k = np.concatenate([np.ones(n, bool), k])
        fused = fuse_with_odometry(xy, odo, known=k)
        if fused.fits:
            return [replace(f, xy=fused.xy[n + i]) for i, f in enumerate(images)
                    if np.isfinite(fused.xy[n + i]).all()]
        k = k[n:]
    return smoothed([f for f, ok in zip(images, k, strict=True) if ok],
                    [q for q, ok in zip(seqs, k, strict=True) if ok])


LearnPath = list[tuple[int, float, float]]  # (estimate seq, x, y) of the last two frames


def path_gate(path: LearnPath, est: Estimate, accuracy_m: float) -> tuple[LearnPath, str | None]:
    """Gates 1 and 2 of a frame: the session's new path, and the gate that stops the frame
    (``confident``, ``path`` or ``accuracy``; None: it passes). The path holds the tracked
    frames, cleared by one that is not tracked (``confident``). ``accuracy``: a tracked frame
    on the path whose ``accuracy_m`` is above ``accuracy_m``; it teaches only where the
    learner's own two-view geometry locates it (``Learner.observe``)."""
    if est.status != "tracking" or est.lost:
        return [], "confident"
    new = [*path, (est.seq, est.x, est.y)][-2:]
    if len(path) < 2 or path[0][0] != est.seq - 2 or path[1][0] != est.seq - 1:
        return new, "path"
    predicted = 2 * np.array(path[1][1:]) - np.array(path[0][1:])
    if float(np.linalg.norm(predicted - np.array([est.x, est.y]))) > PATH_TOLERANCE_M:
        return new, "path"
    return new, ("accuracy" if est.accuracy_m > accuracy_m else None)


def located(images: list[NewImage], seqs: list[int], odometry: list[np.ndarray | None],
            known: list[bool]) -> Context:
    """The located (not bridged) images sent with odometry, as (seq, xy, odometry)."""
    return [(q, f.xy, o) for f, q, o, ok in zip(images, seqs, odometry, known, strict=True)
            if ok and o is not None]


def wheels_place(before: Context, here: np.ndarray) -> np.ndarray | None:
    """Where the robot's wheels put a frame with odometry ``here`` after the taught frames
    ``before`` (oldest first): its odometry aligned to their located positions
    (``fuse_with_odometry``, their last ``positions.WINDOW_M`` of travel). None where they do
    not spread (nothing gives the wheels' heading on the map)."""
    if len(before) < 3:
        return None
    xy = np.array([c[1] for c in before] + [np.zeros(2)], float)
    odo = np.array([c[2] for c in before] + [here], float)
    known = np.ones(len(xy), bool)
    known[-1] = False
    at = fuse_with_odometry(xy, odo, known=known).xy[-1]
    return at if np.isfinite(at).all() else None


def wheels_turned(before: Context, turn: float, here: np.ndarray) -> np.ndarray | None:
    """Where the robot's wheels put a frame with odometry ``here`` after the last taught frame
    of ``before``, their step turned into the map by ``turn`` (the map heading of that
    frame's located camera less its odometry yaw)."""
    if not before:
        return None
    _, a_xy, a_odom = before[-1]
    return turned(a_xy, turn, here - a_odom)


def turned(xy: np.ndarray, turn: float, step: np.ndarray) -> np.ndarray:
    """``xy`` plus the wheels' ``step`` turned into the map by ``turn``."""
    z = complex(np.cos(turn), np.sin(turn)) * complex(*step)
    return xy + np.array([z.real, z.imag])


def wheels_agree(before: Context, at: np.ndarray, here: np.ndarray,
                 turn: float | None = None) -> bool:
    """Whether the robot's wheels agree with a taught frame located at ``at`` (odometry
    ``here``) after a stretch it did not teach, the taught frames ``before`` it (oldest
    first; the last one starts the stretch): each place the wheels give it is within
    ``BRIDGE_TOLERANCE_M`` of ``at``, so a robot carried off in the stretch, along its way or
    across it, disagrees. The places: ``wheels_turned`` by ``turn`` (the stretch's first
    frame's located heading less its odometry yaw: from a session's first taught frame on)
    and ``wheels_place`` (where the frames before spread). Where neither applies, the
    distance the wheels travelled since the last of them agrees with the located one within
    ``BRIDGE_TOLERANCE_M`` (a carry across the way passes this check)."""
    places = [p for p in (wheels_place(before, here),
                          None if turn is None else wheels_turned(before, turn, here))
              if p is not None]
    if places:
        return all(float(np.linalg.norm(p - at)) <= BRIDGE_TOLERANCE_M for p in places)
    if not before:
        return False
    _, a_xy, a_odom = before[-1]
    return abs(float(np.linalg.norm(at - a_xy)) - float(np.linalg.norm(here - a_odom))) \
        <= BRIDGE_TOLERANCE_M


@dataclass
class LeadSteps:
    """A lead's steps seen by the images: each pair of its frames matched once, and each
    frame's structure from the frame before triangulated once, however many of the chain's
    candidate links (``lead_chain``) use them."""

    m: RouteMap
    features: list[Features]
    odometry: list[np.ndarray]  # each frame's odometry position (the wheels' path)
    _pairs: dict[tuple[int, int, bool], tuple[np.ndarray, np.ndarray]] = field(
        default_factory=dict, init=False)
    _structures: dict[tuple[int, int, bool], Structure | None] = field(
        default_factory=dict, init=False)

    def _codes(self, i: int, second: bool) -> Features | None:
        return self.features[i].second if second else self.features[i]

    def _matches(self, x: int, y: int, second: bool) -> tuple[np.ndarray, np.ndarray]:
        key = (x, y, second)
        if key not in self._pairs:
            fx, fy = self._codes(x, second), self._codes(y, second)
            assert fx is not None and fy is not None
            self._pairs[key] = self.m.frame_pairs(fx.codes, fy.codes, GeometryParams().delta,
                                                  second)
        return self._pairs[key]

    def _structure(self, b: int, a: int, second: bool) -> Structure | None:
        """Frame ``b``'s structure from its matches with ``a``, scaled by the wheels' step
        between them."""
        key = (b, a, second)
        if key not in self._structures:
            geometry = self.m.geometry
            assert geometry is not None
            fa, fb = self._codes(a, second), self._codes(b, second)
            assert fa is not None and fb is not None
            base = float(np.linalg.norm(self.odometry[b] - self.odometry[a]))
            try:
                st = triangulate(fb.keypoints, fa.keypoints, self._matches(b, a, second), base,
                                 geometry.k, GeometryParams().min_inliers)
            except cv2.error:  # a degenerate configuration: no geometry
                st = None
            self._structures[key] = st
        return self._structures[key]

    def seen(self, a: int, b: int, c: int) -> float | None:
        """How far frame ``c`` stands from frame ``b``, seen by three frames: ``b``'s
        structure from ``a``, the wheels' step from ``a`` to ``b`` its scale, and ``c``
        located on it (on a map of two feature types RootSIFT's, XFeat's where RootSIFT's
        gives none). None where neither gives geometry, or on a map without the camera."""
        geometry = self.m.geometry
        if geometry is None:
            return None
        for second in (False, True)[:1 + (self.m.second is not None)]:
            fc = self._codes(c, second)
            if fc is None or self._codes(a, second) is None or self._codes(b, second) is None:
                continue
            st = self._structure(b, a, second)
            if st is None:
                continue
            try:
                off = locate(fc.keypoints, self._matches(c, b, second), st, geometry.k,
                             GeometryParams().min_inliers)
            except cv2.error:
                off = None
            if off is not None:
                return float(np.hypot(off.right_m, off.ahead_m))
        return None

    def follows(self, a: int, b: int, c: int) -> bool:
        """Whether frame ``c`` follows frame ``b`` as the robot's wheels say: the step between
        them seen by the images (``seen``) within a factor ``LEAD_RATIO`` of the wheels' step
        from ``b`` to ``c``; both the wheels' steps, ``a`` to ``b`` and ``b`` to ``c``, at
        least ``LEAD_MIN_STEP_M``."""
        odo = self.odometry
        base = float(np.linalg.norm(odo[b] - odo[a]))
        step = float(np.linalg.norm(odo[c] - odo[b]))
        if min(base, step) < LEAD_MIN_STEP_M:
            return False
        seen = self.seen(a, b, c)
        return seen is not None and 1.0 / LEAD_RATIO <= seen / step <= LEAD_RATIO


def lead_chain(m: RouteMap, frames: list[Held]) -> list[int]:
    """The frames (indices, newest first) linked back from the last one, each step one the
    wheels made (``LeadSteps.follows``, from one of the two frames before, with one of the two
    before that): where no link holds, the chain ends (the robot may have been carried
    there). On a map without the camera no link holds: the chain is the last frame alone."""
    steps = LeadSteps(m, [f[0].features for f in frames], [f[2] for f in frames])
    chain = [len(frames) - 1]
    while True:
        c = chain[-1]
        nxt = next((b for b in (c - 1, c - 2) for a in (b - 1, b - 2)
                    if a >= 0 and steps.follows(a, b, c)), None)
        if nxt is None:
            return chain
        chain.append(nxt)


def experience_id(robot_id: str, created: float) -> str:
    """The experience a session teaches: the same on every replica (robot id and the session's
    creation time)."""
    digest = hashlib.blake2b(f"{robot_id}\0{created!r}".encode(), digest_size=5).hexdigest()
    return f"e{digest}"


class Learner:
    """The learning robots' collections of one service; thread-safe. ``submit`` runs
    ``observe`` on the learner's own threads; every other call first waits for the frames
    handed over before it."""

    def __init__(self, gates: LearnGates, commit: Commit,
                 counted: Callable[[str], None] | None = None) -> None:
        self.gates = gates
        self._commit = commit
        # each frame's outcome (``OUTCOMES``), for the service's metrics
        self._counted = counted or (lambda outcome: None)
        self._trails: dict[str, _Trail] = {}
        self._usage: dict[str, Usage] = {}
        self._levels: dict[str, float] = {}  # map version -> same_light_level
        self._bases: dict[str, str] = {}  # map version -> base_identity
        self._lock = threading.Lock()
        self._queue = LearnQueue()  # ``submit``: the gates off the frame path

    @property
    def running(self) -> bool:
        """Whether the learner's threads run (from the first ``submit`` to ``flush_all``)."""
        return self._queue.running

    # ---- use statistics of experiences (every session) -------------------------------------
    def used(self, map_name: str, exp_id: str, now: float) -> None:
        with self._lock:
            u = self._usage.setdefault(map_name, {})
            n, _ = u.get(exp_id, (0, 0.0))
            u[exp_id] = (n + 1, now)

    def usage(self, map_name: str, clear: bool = False) -> Usage:
        with self._lock:
            u = self._usage.get(map_name, {})
            if clear:
                self._usage.pop(map_name, None)
            return dict(u)

    def restore_usage(self, map_name: str, usage: Usage) -> None:
        """Count again the uses ``usage(clear=True)`` took for a write that wrote nothing."""
        with self._lock:
            u = self._usage.setdefault(map_name, {})
            for exp_id, (n, last) in usage.items():
                have, was = u.get(exp_id, (0, 0.0))
                u[exp_id] = (have + n, max(last, was))

    # ---- learning sessions -----------------------------------------------------------------
    def stats(self, robot_id: str) -> dict[str, int]:
        """A learning robot's frames seen, taught (``odometry``: of them, sent with the
        robot's odometry), images waiting, and frames stopped by each gate (``confident``,
        ``path``, ``appearance``, ``located``, ``place``), its frames handed over before
        included."""
        self._queue.drain(key=robot_id)
        got = self.progress(robot_id)
        return {} if got is None else got[1]

    def progress(self, robot_id: str, wait_s: float = 0.0
                 ) -> tuple[str, dict[str, int]] | None:
        """(experience id, ``stats``) of a robot learning on this replica, the frames handed
        over before included where their gates run within ``wait_s`` (0: those that have
        run); None where it has no collection here."""
        if wait_s > 0:
            self._queue.drain(wait_s, key=robot_id)
        with self._lock:
            t = self._trails.get(robot_id)
            return None if t is None else (t.exp_id, self._counts(t))

    @staticmethod
    def _counts(t: _Trail) -> dict[str, int]:
        return {"seen": t.seen, "taught": t.taught, "bridged": t.bridged,
                "odometry": t.with_odometry, "waiting": len(t.pending), **t.refused}

    def _refuse(self, t: _Trail, gate: str) -> None:
        t.refuse(gate)
        self._counted(gate)

    def submit(self, robot_id: str, created: float, condition: str | None, m: RouteMap,
               features: Features, est: Estimate, stopped: str | None,
               odom: Odometry | None = None) -> None:
        """``observe`` on the robot's learner thread, after the robot's earlier frames
        (service/engine/learn_queue.py): the frame's answer does not wait for its gates."""
        self._queue.submit(robot_id, partial(self.observe, robot_id, created, condition, m,
                                             features, est, stopped, odom))

    def observe(self, robot_id: str, created: float, condition: str | None, m: RouteMap,
                features: Features, est: Estimate, stopped: str | None,
                odom: Odometry | None = None) -> None:
        """One estimate of a learning session, ``stopped`` by gate 1 or 2 (``path_gate`` on
        the session's path) or not: collect the frame if it passes the other gates (a frame
        stopped by gate 1, 2 or 4 is held for the wheels to bridge, and a taught one bridges
        the frames held before it), hand the collection to the writer when it is full (no
        map write here). On a map of two feature types the frame's both sets are kept;
        ``odom``: the odometry pose the robot sent with the frame (``placed`` uses it)."""
        base = self.identity(m)
        exp_id = experience_id(robot_id, created)
        with self._lock:
            t = self._trails.get(robot_id)
        if t is not None and (t.map_name != m.name or t.exp_id != exp_id):
            # the robot's earlier session's collection (it ended through another replica,
            # or moved to another map): written into its own experience, not continued
            self.flush(robot_id, end=True)
        with self._lock:
            t = self._trails.get(robot_id)
            if t is None:
                t = self._trails[robot_id] = _Trail(exp_id, m.name, condition)
            if t.base != base and not t.pending:  # new, or reset onto a rebuilt map: the
                # frames before were placed in another map's frame
                t.base, t.context, t.anchor, t.turn, t.gap, t.gap_m, t.lead = base, [], None, \
                    None, [], 0.0, []
            t.seen += 1
            t.last_seen = time.monotonic()
            xy = np.array([est.x, est.y])
            if stopped not in (None, "accuracy"):
                self._refuse(t, str(stopped))
                self._hold(t, m, features, est.seq, odom)
                return
        at: np.ndarray | None = None
        heading: float | None = None
        gate: str | None = "appearance"
        if self._new_appearance(m, features, xy):
            at, heading = self._located(m, features, xy)
            gate = None if at is not None else "located"
            if stopped == "accuracy" and (gate is not None or m.geometry is None):
                gate = "confident"  # neither the estimate nor the geometry is sure of it
        with self._lock:
            radius = PLACE_SPACINGS * base_spacing(m)
            if gate is None and any(float(np.linalg.norm(f.xy - xy)) < radius
                                    for f in t.pending):
                gate = "place"  # one image per place and experience
            if gate is not None or at is None:
                self._refuse(t, gate or "located")
                if gate in ("located", "confident"):
                    self._hold(t, m, features, est.seq, odom)
                return
            t.taught += 1
            self._counted("taught")
            here = None if odom is None else np.array([odom.x, odom.y], float)
            turn = None if odom is None or heading is None else heading - odom.yaw
            held = self._bridge(t, at, est.seq, here, turn)
            lead, t.lead = t.lead, []  # held before the session's first taught frame
            t.pending.append(NewImage.of(features, at, f"{t.exp_id}/{est.seq:06d}",
                                         second=m.second is not None))
            t.seqs.append(est.seq)
            t.odometry.append(here)
            t.known.append(True)
            t.with_odometry += odom is not None
        if lead and here is not None and turn is not None:
            first = (NewImage.of(features, at, "", second=m.second is not None), est.seq, here)
            held += self._lead(m, lead, first, turn)
        if held:
            self._bridged(t, m, held)
        with self._lock:
            full = len(t.pending) >= self.gates.commit_images
        if full:
            self.flush(robot_id)

    @staticmethod
    def _hold(t: _Trail, m: RouteMap, features: Features, seq: int,
              odom: Odometry | None) -> None:
        """Keep a refused frame of a learning robot that sends its odometry: after a taught
        one, the wheels may bridge it to the next taught frame (``_bridge``); before the
        session's first taught frame it joins the session's lead (``_lead``: its last
        ``BRIDGE_M`` of travel and ``BRIDGE_FRAMES`` kept). Under the lock."""
        if odom is None:
            t.anchor, t.gap, t.gap_m, t.lead = None, [], 0.0, []
            return
        here = np.array([odom.x, odom.y], float)

        def held() -> Held:  # the frame's features copied, for a frame that is kept
            return NewImage.of(features, np.full(2, np.nan), f"{t.exp_id}/{seq:06d}",
                               second=m.second is not None), seq, here

        if t.anchor is not None:
            t.gap_m += float(np.linalg.norm(here - (t.gap[-1][2] if t.gap else t.anchor[2])))
            if t.gap_m <= BRIDGE_M and len(t.gap) < BRIDGE_FRAMES:
                t.gap.append(held())
                return
            t.anchor, t.gap, t.gap_m = None, [], 0.0
        if t.taught:  # the lead is the session's start only
            return
        t.lead = [*t.lead, held()][-BRIDGE_FRAMES:]
        odo = np.array([o for _, _, o in t.lead], float)
        back = np.concatenate([np.cumsum(np.linalg.norm(np.diff(odo, axis=0),
                                                        axis=1)[::-1])[::-1], [0.0]])
        t.lead = [f for f, travel in zip(t.lead, back, strict=True) if travel <= BRIDGE_M]

    @staticmethod
    def _lead(m: RouteMap, lead: list[Held], first: Held, turn: float) -> list[Held]:
        """A session's lead taught by the wheels back from its first taught frame ``first``
        (``turn``: its located heading less its odometry yaw): the frames of the lead's
        ``lead_chain`` to it, each placed by the wheels' step back from it turned into the
        map."""
        frames = [*lead, first]
        at, here = first[0].xy, first[2]
        return [(replace(frames[i][0], xy=turned(at, turn, frames[i][2] - here)),
                 frames[i][1], frames[i][2]) for i in lead_chain(m, frames)[1:]]

    @staticmethod
    def _bridge(t: _Trail, at: np.ndarray, seq: int, here: np.ndarray | None,
                turn: float | None = None) -> list[Held]:
        """A taught frame at ``at`` (odometry ``here``): the frames held since the last taught
        one, placed by the wheels between the two, where the wheels agree with it
        (``wheels_agree``). Under the lock."""
        gap, anchor, anchor_turn = t.gap, t.anchor, t.turn
        t.gap, t.gap_m = [], 0.0
        t.anchor = None if here is None else (seq, at, here)
        t.turn = None if here is None else turn
        if here is None or anchor is None or not gap:
            return []
        _, a_xy, a_odom = anchor
        chord_map, chord_odom = at - a_xy, here - a_odom
        if float(np.linalg.norm(chord_odom)) < 1e-6 or \
                not wheels_agree(Learner._before(t), at, here, anchor_turn):
            return []
        # the similarity that maps the two odometry positions onto the two located ones
        factor = complex(*chord_map) / complex(*chord_odom)
        out = []
        for img, gseq, odom in gap:
            z = factor * complex(*(odom - a_odom))
            out.append((replace(img, xy=a_xy + np.array([z.real, z.imag])), gseq, odom))
        return out

    @staticmethod
    def _before(t: _Trail) -> Context:
        """The robot's located taught frames with odometry, oldest first (located frames join
        the collection in frame order; bridged ones, which join later, are left out), the
        last batch's included (the last ``CONTEXT_FRAMES``). Under the lock."""
        return (t.context + located(t.pending, t.seqs, t.odometry, t.known))[-CONTEXT_FRAMES:]

    def _bridged(self, t: _Trail, m: RouteMap, held: list[Held]) -> None:
        """Held frames bridged by the wheels join the collection where they add a new
        appearance (gate 3 at their bridged place) and a new place (gate 5)."""
        new = []
        for img, seq, odom in held:
            if self._new_appearance(m, img.features, img.xy):
                new.append((img, seq, odom))
        radius = PLACE_SPACINGS * base_spacing(m)
        with self._lock:
            for img, seq, odom in new:
                if any(float(np.linalg.norm(f.xy - img.xy)) < radius for f in t.pending):
                    continue
                t.pending.append(img)
                t.seqs.append(seq)
                t.odometry.append(odom)
                t.known.append(False)
                t.bridged += 1
                self._counted("bridged")

    def identity(self, m: RouteMap) -> str:
        """The map's ``base_identity``, kept per version."""
        return self._per_version(self._bases, m, base_identity)

    def level(self, m: RouteMap) -> float:
        """The map's same-light level, kept per version."""
        return self._per_version(self._levels, m, same_light_level)

    def _per_version(self, kept: dict[str, T], m: RouteMap, compute: Callable[[RouteMap], T]
                     ) -> T:
        """``compute(m)``, computed once per map version (its checksum) and kept in ``kept``."""
        key = str(m.meta.get("checksum"))
        with self._lock:
            have = kept.get(key)
        if have is None:
            have = compute(m)
            with self._lock:
                kept[key] = have
        return have

    def _new_appearance(self, m: RouteMap, features: Features, xy: np.ndarray) -> bool:
        """Gate 3: every layer's image near the estimate matches below the weak share of the
        map's same-light level."""
        ids = self._near_images(m, xy)
        if not len(ids):
            return False
        best = float(np.max(m.similarity(features, ids)))
        return best < self.gates.weak_ratio * self.level(m)

    @staticmethod
    def _near_images(m: RouteMap, xy: np.ndarray) -> np.ndarray:
        ids, dist = m.nearest_per_layer(xy[None, :])
        return ids[0][dist[0] <= GAP_SPACINGS * base_spacing(m)]

    def _located(self, m: RouteMap, features: Features, xy: np.ndarray
                 ) -> tuple[np.ndarray | None, float | None]:
        """Gate 4: where the geometry places the frame, near the estimate; None where it does
        not (maps without the camera: the estimate, the gate does not apply). On a map of two
        feature types an image the first set (RootSIFT) does not locate the frame at is tried
        with the second (XFeat)."""
        geometry = m.geometry
        if geometry is None:
            return xy, None
        tries = [(geometry, features)]
        if m.second_geometry is not None and features.second is not None:
            tries.append((m.second_geometry, features.second))
        ids = self._near_images(m, xy)
        order = ids[np.argsort(-m.similarity(features, ids), kind="stable")]
        p = GeometryParams()
        spacing = base_spacing(m)
        for image in order[:GEOMETRY_TRIES]:
            image = int(image)
            tangent = path_tangent(m.positions, image, spacing)
            if tangent is None:
                continue
            for geo, feats in tries:
                off = geo.locate(feats, image, p)
                if off is None:
                    continue
                at = along_path(m.positions[image], tangent, off.right_m, off.ahead_m)
                if np.isfinite(at).all() and \
                        float(np.linalg.norm(at - xy)) <= LOCATED_TOLERANCE_M:
                    return np.asarray(at, float), off.heading
        return None, None

    def flush(self, robot_id: str, end: bool = False, reset: bool = False) -> None:
        """Hand the robot's collected images to the writer (and with ``end`` forget it), its
        frames handed over before included (not other robots': their backlog does not hold up
        this robot's reset or end); ``reset``: the session was reset (the robot may stand
        elsewhere now), so its lead is dropped."""
        self._queue.drain(key=robot_id)
        with self._lock:
            t = self._trails.pop(robot_id, None) if end else self._trails.get(robot_id)
            if t is None:
                return
            if reset:
                t.lead = []
            images, t.pending = t.pending, []
            seqs, t.seqs = t.seqs, []
            odometry, t.odometry = t.odometry, []
            known, t.known = t.known, []
            context, base = t.context, t.base
            t.context = located(images, seqs, odometry, known)[-CONTEXT_FRAMES:]
        if images:
            self._commit(t.map_name, t.exp_id, placed(images, seqs, odometry, known, context),
                         t.condition, robot_id, base)

    def flush_idle(self, idle_s: float, now: float | None = None) -> None:
        """Write the collections of robots that sent this replica no frame for ``idle_s``
        (their frames go to another replica now, or they stopped; the trail stays)."""
        now = time.monotonic() if now is None else now
        self._queue.drain()
        with self._lock:
            robots = [rid for rid, t in self._trails.items()
                      if t.pending and now - t.last_seen > idle_s]
        for rid in robots:
            self.flush(rid)

    def flush_all(self) -> None:
        """At shutdown: write every learning robot's collected images (they live in memory
        only; a session that continues after a restart starts a new collection), and stop
        the learner's threads."""
        self._queue.close()
        with self._lock:
            robots = list(self._trails)
        for rid in robots:
            self.flush(rid, end=True)
