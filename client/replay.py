"""Replay a recorded round against a map through any transport and collect what came back."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from client.dataset import Round
from client.runs import Run, frame_sequence, odometry_poses
from client.transports import Client
from service.api.models import Estimate, SessionInfo


@dataclass(frozen=True)
class ReplayConfig:
    map_name: str | None = None
    estimator: str = "dpso"
    params: dict[str, Any] = field(default_factory=dict)
    seed: int = 0
    start: int = 0  # first image (wraps around the loop)
    speed: float = 1.0  # k > 1: every k-th image; 1/r: each image r times (Sec. 7.1)
    kidnap: bool = False  # jump by n/2 images at the middle of the run (Sec. 7.1)
    length: int | None = None  # iterations per run (default: one round)
    repeat: int = 1  # runs from evenly spaced start images (seed + run index)
    odometry: bool = True  # send the round's odometry.csv with the frames, where it has one
    learn: bool = False  # the runs teach the map an experience (service/maps/experiences.py)
    condition: str | None = None  # the light of the round: the experience's tag


def replay(client: Client, rnd: Round, cfg: ReplayConfig, *, robot_id: str = "replay",
           progress: bool = False,
           on_frame: Callable[[int, Estimate], None] | None = None,
           on_end: Callable[[SessionInfo], None] | None = None) -> list[Run]:
    """Stream the round's frames in order to a session, once per run; ``on_end``: the
    session as it stands after each run's last frame, before it is deleted (a learning
    session's ``learning``: what it taught)."""
    n = len(rnd)
    dt = float(np.median(np.diff(rnd.t))) if rnd.t is not None and n > 1 else 1.0
    cache: dict[int, bytes] = {}
    runs: list[Run] = []
    starts = [(cfg.start + k * n // cfg.repeat) % n for k in range(cfg.repeat)]
    for k, start in enumerate(starts):
        seq = frame_sequence(n, start, cfg.speed, cfg.kidnap, cfg.length)
        poses = odometry_poses(rnd.odometry if cfg.odometry else None, seq)
        seed = cfg.seed + k
        client.create_session(robot_id, cfg.map_name, cfg.estimator, cfg.params, seed,
                              learn=cfg.learn, condition=cfg.condition)
        it: Iterable[int] = range(len(seq))
        if progress:
            from tqdm import tqdm

            it = tqdm(it, desc=f"run {k + 1}/{len(starts)} (start {start})", unit="frame")
        estimates: list[Estimate] = []
        latency: list[float] = []
        for i in it:
            q = int(seq[i])
            if q not in cache:
                cache[q] = rnd.image_path(q).read_bytes()
            t0 = time.perf_counter()
            est = client.localize(robot_id, cache[q], t=i * dt, seq=i, odom=poses[i])
            latency.append(1e3 * (time.perf_counter() - t0))
            estimates.append(est)
            if on_frame:
                on_frame(i, est)
        if on_end is not None:
            on_end(client.session(robot_id))
        client.delete_session(robot_id)
        runs.append(Run.from_estimates(
            estimates, estimator=cfg.estimator, start=start, seed=seed, frames=seq,
            true_xy=rnd.reference_xy[seq], dt=dt, kidnap=cfg.kidnap,
            latency_ms=np.array(latency)))
    return runs
