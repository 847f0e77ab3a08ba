"""Replay a recorded round against a map through any transport and collect what came back."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from client.dataset import Round
from client.experiments import frame_sequence, true_speed
from client.transports import Client
from service.models import Estimate


@dataclass(frozen=True)
class ReplayConfig:
    map_name: str | None = None
    estimator: str = "dpso"
    params: dict = field(default_factory=dict)
    seed: int = 0
    start: int = 0  # first image (wraps around the loop)
    speed: float = 1.0  # k > 1: every k-th image; 1/r: each image r times (Sec. 7.1)
    kidnap: bool = False  # jump by n/2 images at the middle of the run (Sec. 7.1)
    length: int | None = None  # iterations per run (default: one round)
    repeat: int = 1  # runs from evenly spaced start images (seed + run index)


@dataclass
class ReplayRun:
    start: int
    seed: int
    frames: np.ndarray  # image index per iteration
    estimates: list[Estimate]
    latency_ms: np.ndarray  # as seen by the client
    true_xy: np.ndarray
    dt: float
    kidnap: bool

    @property
    def est_xy(self) -> np.ndarray:
        return np.array([[e.x, e.y] for e in self.estimates])

    @property
    def errors(self) -> np.ndarray:
        return np.linalg.norm(self.est_xy - self.true_xy, axis=1)

    @property
    def true_speed(self) -> np.ndarray:
        return true_speed(self.true_xy, self.dt)


def replay(client: Client, rnd: Round, cfg: ReplayConfig, robot_id: str = "replay",
           progress: bool = False,
           on_frame: Callable[[int, Estimate], None] | None = None) -> list[ReplayRun]:
    """Stream the round's frames in order to a session, once per run."""
    n = len(rnd)
    dt = float(np.median(np.diff(rnd.t))) if rnd.t is not None and n > 1 else 1.0
    cache: dict[int, bytes] = {}
    runs = []
    starts = [(cfg.start + k * n // cfg.repeat) % n for k in range(cfg.repeat)]
    for k, start in enumerate(starts):
        seq = frame_sequence(n, start, cfg.speed, cfg.kidnap, cfg.length)
        seed = cfg.seed + k
        client.create_session(robot_id, cfg.map_name, cfg.estimator, cfg.params, seed)
        it = range(len(seq))
        if progress:
            from tqdm import tqdm

            it = tqdm(it, desc=f"run {k + 1}/{len(starts)} (start {start})", unit="frame")
        estimates, latency = [], []
        for i in it:
            q = int(seq[i])
            if q not in cache:
                cache[q] = rnd.image_path(q).read_bytes()
            t0 = time.perf_counter()
            est = client.localize(robot_id, cache[q], t=i * dt, seq=i)
            latency.append(1e3 * (time.perf_counter() - t0))
            estimates.append(est)
            if on_frame:
                on_frame(i, est)
        client.delete_session(robot_id)
        runs.append(ReplayRun(start, seed, seq, estimates, np.array(latency),
                              rnd.reference_xy[seq], dt, cfg.kidnap))
    return runs
