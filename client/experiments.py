"""The papers' experiment protocol, in process (journal Sec. 6-7).

A round is replayed against a map from a chosen start image (wrapping around the loop), at a
simulated speed (every k-th image, or each image repeated), optionally kidnapped at the middle
of the run (image index + n/2). Many runs over the same frames share one lazily filled table of
similarities m(frame, map image): a value is computed (batched) the first time any run asks for
it, so repeating runs costs estimator time only. Each run still counts its own comparisons.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from client.dataset import Round
from service.features import Features, extract
from service.localizer import Localizer
from service.route_map import RouteMap


class SimilarityTable:
    """m(query frame q, map image i), computed on first use and kept."""

    def __init__(self, route_map: RouteMap, queries: Sequence[Features]) -> None:
        self.map = route_map
        self.queries = queries
        self.table = np.full((len(queries), route_map.n_images), np.nan, np.float64)
        self.cache_path: Path | None = None  # where ``swarmloc experiment`` keeps it

    @classmethod
    def from_round(cls, route_map: RouteMap, rnd: Round) -> SimilarityTable:
        params = route_map.sift_params
        return cls(route_map, [extract(rnd.load_image(i), params) for i in range(len(rnd))])

    def scores(self, q: int, ids: np.ndarray) -> np.ndarray:
        row = self.table[q]
        missing = ids[np.isnan(row[ids])]
        if len(missing):
            row[missing] = self.map.similarity(self.queries[q].codes, missing)
        return row[ids]


def frame_sequence(n: int, start: int = 0, speed: float = 1.0, kidnap: bool = False,
                   length: int | None = None) -> np.ndarray:
    """Query image indices of one run (Sec. 6-7.1).

    ``speed`` k > 1 uses every k-th image; 1/r repeats each image r times. ``kidnap`` adds
    n/2 to the image index from the middle of the run on.
    """
    length = length or n
    if speed >= 1:
        seq = start + np.arange(length) * round(speed)
    else:
        seq = start + np.arange(length) // round(1 / speed)
    seq = seq % n
    if kidnap:
        seq[length // 2 :] = (seq[length // 2 :] + n // 2) % n
    return seq


@dataclass
class RunResult:
    estimator: str
    frames: np.ndarray  # query image index per iteration
    est_xy: np.ndarray
    true_xy: np.ndarray
    comparisons: np.ndarray
    status: list[str]
    speed: np.ndarray  # estimated m/s
    true_speed: np.ndarray  # m/s between consecutive iterations
    scores: np.ndarray
    step_ms: np.ndarray  # estimator time per frame, feature extraction excluded
    accuracy_m: np.ndarray = field(default_factory=lambda: np.zeros(0))  # 68 % radius
    lost: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def errors(self) -> np.ndarray:
        return np.linalg.norm(self.est_xy - self.true_xy, axis=1)


def run(route_map: RouteMap, table: SimilarityTable, rnd: Round, estimator: str = "dpso",
        params: dict[str, Any] | None = None, seed: int = 0, start: int = 0, speed: float = 1.0,
        kidnap: bool = False, length: int | None = None) -> RunResult:
    """Replay one run of the protocol in process and collect per-frame results."""
    import time

    n = len(rnd)
    seq = frame_sequence(n, start, speed, kidnap, length)
    truth = rnd.reference_xy
    dt = float(np.median(np.diff(rnd.t))) if rnd.t is not None and n > 1 else 1.0
    loc = Localizer(route_map, estimator, params, seed)
    est, comps, status, spd, scores, ms, acc, lost = [], [], [], [], [], [], [], []
    for it, q in enumerate(seq):
        t0 = time.perf_counter()
        e = loc.estimator.step(lambda ids, q=q: table.scores(int(q), ids), it * dt)
        ms.append(1e3 * (time.perf_counter() - t0))
        est.append(e.position)
        comps.append(e.comparisons)
        status.append(e.status.value)
        spd.append(e.speed_mps)
        scores.append(e.score)
        acc.append(e.accuracy_m)
        lost.append(e.lost)
    true_xy = truth[seq]
    return RunResult(estimator, seq, np.array(est), true_xy, np.array(comps), status,
                     np.array(spd), true_speed(true_xy, dt), np.array(scores), np.array(ms),
                     np.array(acc), np.array(lost, bool))


def true_speed(xy: np.ndarray, dt: float) -> np.ndarray:
    """Speed (m/s) between consecutive iterations; the first repeats the second."""
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    return np.concatenate([step[:1] if len(step) else [0.0], step]) / dt


def frames_until_within(err: np.ndarray, since: int, within_m: float = 5.0, hold: int = 5
                        ) -> int | None:
    """Iterations from ``since`` until the error stays within ``within_m`` for ``hold``
    frames in a row; None if it never does."""
    ok = err[since:] <= within_m
    for i in range(len(ok) - hold + 1):
        if ok[i : i + hold].all():
            return i
    return None


def frames_to_recover(res: RunResult, within_m: float = 5.0, hold: int = 5) -> int | None:
    """Iterations after the kidnapping (middle of the run) until back within ``within_m``."""
    return frames_until_within(res.errors, len(res.errors) // 2, within_m, hold)
