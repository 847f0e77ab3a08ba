"""The papers' experiment protocol (``client.runs``), in process (journal Sec. 6-7).

Many runs over the same frames share one lazily filled table of
similarities m(frame, map image): a value is computed (batched) the first time any run asks for
it, so repeating runs costs estimator time only. Each run still counts its own comparisons.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from client.dataset import Round
from client.runs import Run, frame_sequence, odometry_poses
from service.engine.localizer import Localizer
from service.estimators.fitness import SimilarityFn
from service.maps.route_map import RouteMap
from service.vision.features import Features, extract


def round_features(route_map: RouteMap, rnd: Round) -> list[Features]:
    """Every frame of ``rnd`` extracted with the map's feature parameters."""
    params = route_map.feature_params
    return [extract(rnd.load_image(i), params) for i in range(len(rnd))]


class SimilarityTable:
    """m(query frame q, map image i), computed on first use and kept."""

    def __init__(self, route_map: RouteMap, queries: Sequence[Features]) -> None:
        self.map = route_map
        self.queries = queries
        self.table = np.full((len(queries), route_map.n_images), np.nan, np.float64)
        # a map of two feature types: the first type's own m too (DPSO's vouching), else None
        self.first = np.full_like(self.table, np.nan) if route_map.fusion is not None \
            else None
        self.cache_path: Path | None = None  # where ``swarmloc experiment`` keeps it

    @classmethod
    def from_round(cls, route_map: RouteMap, rnd: Round) -> SimilarityTable:
        return cls(route_map, round_features(route_map, rnd))

    def fresh(self) -> SimilarityTable:
        """An empty table of the same map and frames (a similarity that depends on which
        images a frame compares together, the words matcher's exact pass, is not shared
        between runs)."""
        return SimilarityTable(self.map, self.queries)

    def scores(self, q: int, ids: np.ndarray) -> np.ndarray:
        row = self.table[q]
        if self.first is None:
            missing = ids[np.isnan(row[ids])]
            if len(missing):
                row[missing] = self.map.similarity(self.queries[q], missing)
            return row[ids]
        first = self.first[q]
        missing = ids[np.isnan(row[ids]) | np.isnan(first[ids])]
        if len(missing):
            def record(i: np.ndarray, m: np.ndarray) -> None:
                first[i] = m
            row[missing] = self.map.similarity(self.queries[q], missing, first=record)
        return row[ids]

    def first_of(self, q: int) -> SimilarityFn | None:
        """The first feature type's own m of frame ``q`` for the images ``scores`` compared
        (a map of two types; None otherwise)."""
        if self.first is None:
            return None
        row = self.first[q]
        return lambda ids: row[ids]


def run(route_map: RouteMap, table: SimilarityTable, rnd: Round, estimator: str = "dpso",
        params: dict[str, Any] | None = None, *, seed: int = 0, start: int = 0,
        speed: float = 1.0, kidnap: bool = False, length: int | None = None,
        odometry: bool = False) -> Run:
    """Replay one run of the protocol in process (``latency_ms``: the estimator's step);
    with ``odometry``, each frame carries the round's odometry (``odometry.csv``, sent as
    ``client.runs.odometry_poses`` gives it)."""
    import time

    n = len(rnd)
    seq = frame_sequence(n, start, speed, kidnap, length)
    if odometry and rnd.odometry is None:
        raise ValueError(f"round {rnd.name} has no odometry.csv")
    poses = odometry_poses(rnd.odometry if odometry else None, seq)
    dt = float(np.median(np.diff(rnd.t))) if rnd.t is not None and n > 1 else 1.0
    loc = Localizer(route_map, estimator, params, seed)
    est: list[np.ndarray] = []
    status: list[str] = []
    comps, spd, head, scores, ms, acc, lost, located, source = ([] for _ in range(9))
    for it, q in enumerate(seq):
        t0 = time.perf_counter()
        motion = loc.take_odometry(poses[it])
        loc.seed_places(table.queries[q].codes)  # the place index, while searching
        e = loc.estimator.step(partial(table.scores, int(q)), it * dt,
                               loc.locator(table.queries[q]), motion,
                               first=table.first_of(int(q)))
        ms.append(1e3 * (time.perf_counter() - t0))
        est.append(e.position)
        comps.append(e.comparisons)
        status.append(e.status.value)
        spd.append(e.speed_mps)
        head.append(e.heading)
        scores.append(e.score)
        acc.append(e.accuracy_m)
        lost.append(e.lost)
        located.append(e.located)
        source.append(e.heading_source)
    return Run(estimator=estimator, start=start, seed=seed, frames=seq,
               true_xy=rnd.reference_xy[seq], dt=dt, kidnap=kidnap,
               est_xy=np.array(est).reshape(-1, 2), status=status,
               comparisons=np.array(comps, np.int64), speed=np.array(spd),
               heading=np.array(head), scores=np.array(scores), accuracy_m=np.array(acc),
               lost=np.array(lost, bool), latency_ms=np.array(ms),
               located=np.array(located, bool), heading_sources=source)
