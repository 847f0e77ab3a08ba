"""The estimate stream for viewers: the hub behind ``GET /events`` (service/http/events.py).

``LocalizationService.process_frame`` (the one place an estimate is made, whichever transport
brought the frame) hands every estimate to ``EventHub.publish``. Each connected viewer is a
``Subscriber`` with a buffer keyed by robot: a newer estimate of a robot replaces the one not
yet sent (newest wins, counted in ``swarmloc_events_dropped_total``), so a slow browser never
holds up a robot and its buffer never holds more than one message per robot and kind.

Particle snapshots are opt-in per robot (``?particles=robot-1,robot-2`` or ``*``) and
rate-limited (``particle_interval_s`` per robot, shared by every viewer). While nobody asks
for a robot's particles, nothing reads them; while nobody is connected, ``publish`` returns
after one check.

Wire format (one SSE message per flush, ``data:`` is JSON)::

    {"now": server_time_s, "m": [message, ...]}        messages in the order they happened
    {"k": "e", "robot", "map", "seq", "stamp", "wall", "x", "y", "heading", "speed",
     "accuracy_m", "status", "score", "comparisons", "latency_ms"[, "hypotheses": [[x, y, w]]]}
    {"k": "p", "robot", "map", "xy": [x0, y0, x1, y1, ...]}      particle positions (m)
    {"k": "x", "robot"}                                          the session is gone

Positions are rounded to centimetres and angles to milliradians: an estimate is about
250 bytes instead of the 1.3 kB of the full ``Estimate`` (no covariance matrices).
"""

from __future__ import annotations

import asyncio
import json
import math
import threading
import time
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

import numpy as np

from service.api.models import Estimate
from service.engine.metrics import Metrics

if TYPE_CHECKING:
    from service.engine.localizer import Localizer

ALL = "*"
KEEPALIVE_S = 15.0


def _r(v: float | None, nd: int) -> float | None:
    if v is None or not math.isfinite(v):
        return None
    return round(float(v), nd)


def estimate_message(est: Estimate, wall: float, latency_s: float | None) -> str:
    """The compact JSON of one estimate (see the module docstring)."""
    msg: dict[str, Any] = {
        "k": "e", "robot": est.robot_id, "map": est.frame_id, "seq": est.seq,
        "stamp": _r(est.stamp, 3), "wall": round(wall, 3),
        "x": _r(est.x, 2), "y": _r(est.y, 2), "heading": _r(est.heading, 3),
        "speed": _r(est.speed, 3), "accuracy_m": _r(est.accuracy_m, 2), "status": est.status,
        "score": _r(est.score, 4), "comparisons": est.comparisons,
        "latency_ms": None if latency_s is None else round(1e3 * latency_s, 2),
    }
    if est.experience is not None:  # the learned layer it matched (service/maps/experiences.py)
        msg["experience"] = est.experience
    if est.hypotheses:  # competing places (multi-swarm DPSO), best first
        msg["hypotheses"] = [[_r(h.x, 2), _r(h.y, 2), _r(h.weight, 4)] for h in est.hypotheses]
    return json.dumps(msg, separators=(",", ":"))


def particles_message(robot_id: str, map_name: str, xy: np.ndarray) -> str:
    flat = np.round(np.asarray(xy, float).ravel(), 2).tolist()
    return json.dumps({"k": "p", "robot": robot_id, "map": map_name, "xy": flat},
                      separators=(",", ":"))


class Subscriber:
    """One viewer: pending messages keyed by (kind, robot), newest wins; woken on its loop."""

    def __init__(self, loop: asyncio.AbstractEventLoop, metrics: Metrics,
                 map_name: str | None, particles: frozenset[str]) -> None:
        self.map_name = map_name
        self.particles = particles
        self._loop = loop
        self._metrics = metrics
        self._lock = threading.Lock()
        self._pending: dict[tuple[str, str], str] = {}
        self._signalled = False
        self._ready = asyncio.Event()
        self.closed = False

    def wants(self, map_name: str) -> bool:
        return self.map_name is None or self.map_name == map_name

    def wants_particles(self, robot_id: str) -> bool:
        return ALL in self.particles or robot_id in self.particles

    def offer(self, kind: str, robot_id: str, message: str) -> None:
        """Queue a message (any thread). A newer one of the same kind and robot replaces it."""
        key = (kind, robot_id)
        with self._lock:
            if kind == "x":  # gone: what was pending for the robot is moot
                self._pending.pop(("e", robot_id), None)
                self._pending.pop(("p", robot_id), None)
            elif key in self._pending:
                del self._pending[key]  # re-insert at the end: messages stay in order
                if kind == "e":
                    self._metrics.events_dropped.inc()
            self._pending[key] = message
            if self._signalled:
                return
            self._signalled = True
        self._loop.call_soon_threadsafe(self._ready.set)

    def close(self) -> None:
        """End the stream (any thread): ``take`` returns None from now on."""
        self.closed = True
        self._loop.call_soon_threadsafe(self._ready.set)

    async def take(self, timeout: float) -> list[str] | None:
        """Everything pending, in order (waits up to ``timeout``; [] when nothing came, None
        once the subscriber is closed)."""
        try:
            await asyncio.wait_for(self._ready.wait(), timeout)
        except TimeoutError:
            return []
        if self.closed:
            return None
        with self._lock:
            out = list(self._pending.values())
            self._pending = {}
            self._signalled = False
            self._ready.clear()
        return out


class EventHub:
    """Fan-out of estimates to subscribers; thread-safe, no work while nobody listens."""

    def __init__(self, metrics: Metrics, particle_interval_s: float = 0.5) -> None:
        self.metrics = metrics
        self.particle_interval_s = particle_interval_s
        self._lock = threading.Lock()
        self._subs: tuple[Subscriber, ...] = ()  # replaced, never mutated: read without lock
        self._watched: frozenset[str] = frozenset()  # robots whose particles someone wants
        self._last_particles: dict[str, float] = {}

    @property
    def subscribers(self) -> int:
        return len(self._subs)

    def subscribe(self, loop: asyncio.AbstractEventLoop, map_name: str | None = None,
                  particles: Iterable[str] = ()) -> Subscriber:
        sub = Subscriber(loop, self.metrics, map_name, frozenset(particles))
        with self._lock:
            self._subs = (*self._subs, sub)
            self._update()
        return sub

    def unsubscribe(self, sub: Subscriber) -> None:
        with self._lock:
            self._subs = tuple(s for s in self._subs if s is not sub)
            self._update()
        sub.closed = True

    def _update(self) -> None:
        watched: set[str] = set()
        for s in self._subs:
            watched |= s.particles
        self._watched = frozenset(watched)
        self.metrics.event_subscribers.set(len(self._subs))

    # ---- called by the session layer (worker threads) ------------------------------------
    def particles_due(self, robot_id: str, localizer: Localizer) -> np.ndarray | None:
        """A copy of the robot's particles when a viewer wants them and the interval passed.

        Call it while holding the session's lock (the estimator mutates its particles).
        Nothing is read when nobody watches this robot.
        """
        watched = self._watched
        if not watched or (robot_id not in watched and ALL not in watched):
            return None
        now = time.monotonic()
        if now - self._last_particles.get(robot_id, -math.inf) < self.particle_interval_s:
            return None
        try:
            xy = localizer.estimator.particles()
        except NotImplementedError:  # an estimator without particles: nothing to show
            return None
        if xy is None:
            return None
        self._last_particles[robot_id] = now
        return np.array(xy, float, copy=True)

    def publish(self, est: Estimate, latency_s: float | None = None,
                particles: np.ndarray | None = None) -> None:
        subs = self._subs
        if not subs:
            return
        robot = est.robot_id or ""
        msg = estimate_message(est, time.time(), latency_s)
        pmsg = None if particles is None else particles_message(robot, est.frame_id, particles)
        for s in subs:
            if s.wants(est.frame_id):
                s.offer("e", robot, msg)
                if pmsg is not None and s.wants_particles(robot):
                    s.offer("p", robot, pmsg)
        self.metrics.events_published.inc()

    def close(self) -> None:
        """End every open stream (the server is shutting down)."""
        for s in self._subs:
            s.close()

    def remove(self, robot_id: str) -> None:
        """Tell every viewer that a robot's session is gone (deleted or expired)."""
        self._last_particles.pop(robot_id, None)
        msg = json.dumps({"k": "x", "robot": robot_id}, separators=(",", ":"))
        for s in self._subs:
            s.offer("x", robot_id, msg)
