"""Prometheus metrics of one service instance (own registry: no global state)."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest


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
        self.dropped = Counter("swarmloc_zenoh_dropped_frames_total",
                               "Stale Zenoh frames dropped (a newer one arrived first)",
                               registry=r)
        self.maps = Gauge("swarmloc_maps_loaded", "Maps loaded", registry=r)
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
        return generate_latest(self.registry)
