"""Prometheus metrics of one service instance (own registry: no global state)."""

from __future__ import annotations

from collections.abc import Iterator

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.metrics_core import Metric

#: the content type of ``Metrics.render``: Prometheus text format 0.0.4
PROMETHEUS_TEXT = "text/plain; version=0.0.4; charset=utf-8"


class Metrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.frames = Counter("swarmloc_frames_total", "Frames localized", ["transport"],
                              registry=r)
        self.latency = Histogram(
            "swarmloc_frame_latency_seconds", "Decode + features + estimator time per frame",
            ["transport"], registry=r,
            buckets=(0.005, 0.01, 0.02, 0.03, 0.05, 0.075, 0.1, 0.15, 0.25, 0.5, 1.0, 2.5))
        self.comparisons = Counter("swarmloc_comparisons_total", "Image comparisons made",
                                   registry=r)
        self.rejected = Counter("swarmloc_rejected_inputs_total", "Rejected requests or frames",
                                ["reason"], registry=r)
        self.sessions = Gauge("swarmloc_sessions", "Open robot sessions", registry=r)
        self.expired = Counter("swarmloc_sessions_expired_total", "Sessions expired when idle",
                               registry=r)
        self.sessions_moved = Counter(
            "swarmloc_sessions_moved_total", "Sessions moved live onto a new version of their "
            "map (one that differs only by experiences)", registry=r)
        self.dropped = Counter("swarmloc_zenoh_dropped_frames_total",
                               "Stale Zenoh frames dropped (a newer one arrived first)",
                               registry=r)
        self.maps = Gauge("swarmloc_maps_loaded", "Maps loaded", registry=r)
        self.learned_waiting = Gauge(
            "swarmloc_learned_batches_waiting", "Learned batches handed over and not yet "
            "written (with Redis: not yet in the map's list)", registry=r)
        self.learning_frames = Counter(
            "swarmloc_learning_frames_total", "Frames of learning sessions, by outcome: "
            "taught, bridged, or the gate that stopped them (confident, path, appearance, "
            "located, place)", ["outcome"], registry=r)
        self.event_subscribers = Gauge("swarmloc_event_subscribers",
                                       "Viewers connected to GET /events", registry=r)
        self.events_published = Counter("swarmloc_events_published_total",
                                        "Estimates handed to the event stream (with viewers)",
                                        registry=r)
        self.events_sent = Counter("swarmloc_events_sent_total",
                                   "Event messages written to viewers", registry=r)
        self.events_dropped = Counter(
            "swarmloc_events_dropped_total",
            "Estimates replaced by a newer one of the same robot before a viewer got them",
            registry=r)
        self.map_loads = Counter("swarmloc_map_loads_total", "Map files loaded and verified",
                                 ["source", "result"], registry=r)  # startup|upload|build
        self.map_uploads = Counter("swarmloc_map_uploads_total", "Map uploads (PUT /maps)",
                                   ["result"], registry=r)  # created|replaced|rejected
        self.map_builds = Counter("swarmloc_map_builds_total", "Map build jobs", ["result"],
                                  registry=r)  # submitted|rejected|done|failed
        self.map_build_seconds = Histogram(
            "swarmloc_map_build_seconds", "Duration of map builds", registry=r,
            buckets=(1, 2, 5, 10, 20, 30, 60, 120, 300, 600, 1800))
        self.map_deletes = Counter("swarmloc_map_deletes_total", "Maps deleted", registry=r)

    def render(self) -> bytes:
        """The exposition of this registry, without the ``*_created`` samples (timestamps of
        each counter's creation: prometheus_client's default, usually turned off). Filtered
        here rather than by ``disable_created_metrics()``, which is process-wide state."""
        return generate_latest(_WithoutCreated(self.registry))


class _WithoutCreated:
    """A collector that yields the registry's metrics less their ``*_created`` samples."""

    def __init__(self, registry: CollectorRegistry) -> None:
        self._registry = registry

    def collect(self) -> Iterator[Metric]:
        for metric in self._registry.collect():  # fresh Metric objects on every call
            created = metric.name + "_created"
            metric.samples = [s for s in metric.samples if s.name != created]
            yield metric
