"""``swarmloc bench store``: what the durable default session store (SQLite) costs per frame,
next to the in-process memory store, measured in the same run.

Each store has its own robot on the same map with the same seed and the same frames; the
frames go round-robin over the stores (frame k to every store, then frame k+1), so a change
of machine load during the run weighs on all of them alike, and the order rotates from
frame to frame (the first store of a round steps measurably slower: cold caches). The cost
is that of ``timed_frame`` (client/lab/bench_scale.py): the session look-up, lock and load,
the estimator step, and the store back (for SQLite: one encode and one committed UPDATE).
"""

from __future__ import annotations

import statistics
import tempfile
from dataclasses import dataclass
from pathlib import Path

from client.lab.bench_scale import timed_frame

STORES = ("memory", "sqlite", "sqlite?synchronous=full")


@dataclass(frozen=True)
class StoreCost:
    store: str
    frames: int
    frame_ms: float  # median of load + step + store
    store_ms: float  # median of load + store (what the store adds around the step)
    step_ms: float  # median of the estimator step
    state_bytes: int
    ratio: float  # median over frames of this store's frame time / the first store's


def bench_session_store(maps_dir: str, round_dir: str, frames: int = 200,
                        estimator: str = "dpso", seed: int = 0,
                        stores: tuple[str, ...] = STORES) -> list[StoreCost]:
    """Median per-frame cost of each store (``memory``, ``sqlite`` with synchronous=NORMAL,
    the default, and with synchronous=FULL), their SQLite files in a temporary directory."""
    from typing import cast

    from client.dataset import read_round
    from service.api.models import EstimatorName, SessionConfig
    from service.engine.localization_service import LocalizationService
    from service.engine.sqlite_store import sqlite_url
    from service.engine.state_codec import encode_session
    from service.settings import Settings

    rnd = read_round(round_dir)
    cfg = SessionConfig(estimator=cast(EstimatorName, estimator), seed=seed)
    with tempfile.TemporaryDirectory(prefix="swarmloc-bench-store-") as tmp:
        services: dict[str, LocalizationService] = {}
        maps = None
        for i, name in enumerate(stores):
            url = "memory" if name == "memory" else \
                sqlite_url(Path(tmp) / f"s{i}.sqlite") + name.removeprefix("sqlite")
            services[name] = svc = LocalizationService(
                Settings(maps_dir=Path(maps_dir), zenoh_enabled=False, session_store=url),
                maps=maps)
            maps = svc.maps
            svc.put_session("bench", cfg)
        try:
            loc = services[stores[0]].session("bench").localizer
            feats = [loc.extract(rnd.load_image(i % len(rnd)))
                     for i in range(min(frames, len(rnd)))]
            times: dict[str, list[tuple[float, float, float]]] = {n: [] for n in stores}
            for k in range(frames):  # the first of a round is slower (cold caches): rotate
                for name in stores[k % len(stores):] + stores[:k % len(stores)]:
                    times[name].append(timed_frame(services[name], "bench",
                                                   feats[k % len(feats)], k))
            out = []
            base = times[stores[0]]
            for name, svc in services.items():
                t = times[name]
                size = len(encode_session(svc.session("bench")))
                # paired by frame: every store steps the same state with the same features
                # (same seed), so the step's work is equal and the ratio shows the store's
                ratio = statistics.median(sum(x) / sum(b) for x, b in zip(t, base, strict=True))
                out.append(StoreCost(
                    name, frames, statistics.median(sum(x) for x in t) * 1e3,
                    statistics.median(x[0] + x[2] for x in t) * 1e3,
                    statistics.median(x[1] for x in t) * 1e3, size, ratio))
            return out
        finally:
            for svc in services.values():
                svc.close()
