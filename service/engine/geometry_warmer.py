"""The two-view geometry's structures of a map, built in the background after it is loaded.

A map image's structure (its features' 3-D points from the image and its neighbours,
service/vision/map_geometry.py) and its camera's heading depend on the map alone and are
built the first time a frame is located there: at dusk, where XFeat's geometry takes over,
that cost 19 ms of essential matrix RANSAC per image, about 35 ms per frame on a first pass
over a route (docs/research/performance.md). This worker builds them ahead of the robots
(``MapGeometry.ready``), one image at a time at a bounded share of a core (``duty``), for
every map whose images all fit the geometry's cache; frames find them ready. Nothing changes
but when they are built: a frame that arrives first builds the same itself.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import numpy as np

from service.engine.duty import rest
from service.maps.experiences import base_images
from service.maps.route_map import RouteMap
from service.vision.map_geometry import GeometryParams, MapGeometry

log = logging.getLogger("swarmloc")


class GeometryWarmer:
    """``submit(map)`` queues a map; a daemon thread warms the queued maps and ends when the
    queue is empty (the next ``submit`` starts another); ``close()`` stops at the next image."""

    def __init__(self, duty: float = 0.5,
                 current: Callable[[RouteMap], bool] = lambda m: True) -> None:
        """``current(map)``: whether the map is still the version served (a replaced one,
        e.g. by a learned experience, is left unfinished)."""
        if not 0.0 < duty <= 1.0:
            raise ValueError(f"duty must be in (0, 1], got {duty}")
        self.duty = duty
        self.current = current
        self._queue: list[RouteMap] = []
        self._stop = threading.Event()
        self._idle = threading.Event()
        self._idle.set()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    @property
    def running(self) -> bool:
        """Whether a warming thread is alive now."""
        with self._lock:
            t = self._thread
        return t is not None and t.is_alive()

    def submit(self, m: RouteMap) -> None:
        """Queue ``m``'s structures (both feature types'), if it has the camera and its images
        fit the geometry's cache (a larger map keeps the structures its robots need)."""
        geometries = [g for g in (m.geometry, m.second_geometry) if g is not None]
        if not geometries or m.n_images > min(g.max_cached for g in geometries):
            return
        with self._lock:
            if self._stop.is_set():
                return
            self._idle.clear()
            self._queue.append(m)
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="geometry-warmer",
                                                daemon=True)
                self._thread.start()

    def wait(self, timeout: float) -> bool:
        """Whether every queued map was warmed within ``timeout`` seconds."""
        return self._idle.wait(timeout)

    def close(self, timeout: float = 5.0) -> None:
        self._stop.set()
        with self._lock:
            t = self._thread
        if t is not None:
            t.join(timeout)

    def _next(self) -> RouteMap | None:
        """The next queued map; None (and this thread's end) when there is none or on close."""
        with self._lock:
            if self._queue and not self._stop.is_set():
                return self._queue.pop(0)
            self._thread = None
            self._idle.set()
            return None

    def _run(self) -> None:
        p = GeometryParams()
        while (m := self._next()) is not None:
            try:
                self._warm(m, [g for g in (m.geometry, m.second_geometry) if g is not None], p)
            except Exception:  # a structure that cannot be built is built (or not) on use
                log.exception("map %s: geometry not warmed", m.name)

    def _warm(self, m: RouteMap, geometries: list[MapGeometry], p: GeometryParams) -> None:
        for i in warm_order(m):
            for g in geometries:  # both feature types of an image, then the next image
                if self._stop.is_set() or not self.current(m):
                    return
                t0 = time.perf_counter()
                g.ready(int(i), p)  # its structure and its camera's heading
                rest(t0, self.duty)  # leave the rest of the core to the frames


def warm_order(m: RouteMap) -> np.ndarray:
    """The order a map's images are warmed in: its experiences' images first, in the order
    they were taught, then the map's own images. A new version's learned images are where the
    robots that move onto it find no structure yet (those it shares with the version before
    are carried over, ``carry_geometry``, and skipped at once); a robot following a learning
    one reaches them in the order they were taught."""
    own = base_images(m)
    learned = np.setdiff1d(np.arange(m.n_images), own)
    return np.concatenate([learned, own]).astype(np.int64)
