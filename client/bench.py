"""Benchmarks that print numbers (never asserted in tests)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from client.world import Pose, World
from service.features import Features, extract, match_batch, similarity_bfmatcher
from service.route_map import prune


def _median_ms(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


@dataclass
class SimilarityBench:
    extract_ms: float
    batched_ms_per_comparison: float
    bfmatcher_ms_per_comparison: float
    speedup: float
    k: int
    frame_features: float
    map_features: float
    counts_equal: bool


def bench_similarity(seed: int = 0, k: int = 20, repeats: int = 7) -> SimilarityBench:
    """SIFT extraction per 320x240 frame; batched m(A, B) vs BFMatcher on the same descriptors.

    Frames come from a rendered round; the K map-side sets are pruned like a real map.
    """
    world = World(seed, length_m=160.0)
    poses, t, _ = world.round_trajectory(0)
    frames = [world.render(Pose(*poses[i]), "sunny", t=float(t[i]), noise_seed=i)
              for i in range(0, 2 * (k + 2), 2)]
    extract_ms = float(np.median([_median_ms(lambda f=f: extract(f), 1) for f in frames]))
    feats = [extract(f) for f in frames]
    pruned, _ = prune(feats)
    query = extract(world.render(Pose(*poses[1]), "cloudy", t=float(t[1]), noise_seed=99))
    sets = [p.descriptors for p in pruned[:k]]
    a = query.descriptors
    batched = _median_ms(lambda: match_batch(a, sets), repeats) / k
    bf = _median_ms(lambda: [similarity_bfmatcher(a, b) for b in sets], max(3, repeats // 2)) / k
    counts = match_batch(a, sets).counts.tolist()
    ref = [similarity_bfmatcher(a, b)[0] for b in sets]
    return SimilarityBench(extract_ms, batched, bf, bf / batched, k, float(len(a)),
                           float(np.mean([len(s) for s in sets])), counts == ref)


def features_of_frames(frames: list[np.ndarray]) -> list[Features]:
    return [extract(f) for f in frames]
