"""A map's per-image working data stays within its byte budget, and what the matchers get
from it does not depend on the budget (service/vision/image_cache.py)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from service.engine.localization_service import LocalizationService
from service.maps.route_map import RouteMap, load_map
from service.settings import Settings
from service.vision.image_cache import ImageCache


def test_the_least_recently_used_values_go_first_within_the_budget() -> None:
    cache = ImageCache(limit_bytes=3000)
    made: list[int] = []

    def value(k: int):
        def make() -> np.ndarray:
            made.append(k)
            return np.full(100, k, np.float64)  # 800 bytes
        return make

    for k in (1, 2, 3):
        cache.get(k, value(k))
    cache.get(1, value(1))  # used again: 2 is now the oldest
    cache.get(4, value(4))  # 4 x 800 > 3000: one goes
    assert cache.bytes <= 3000 and cache.keys() == [3, 1, 4]
    assert made == [1, 2, 3, 4]
    assert cache.get(2, value(2))[0] == 2 and made[-1] == 2  # 2 was dropped, made again
    assert cache.get(1, value(1))[0] == 1 and made[-1] == 2  # 1 was kept
    big = cache.get("big", lambda: np.zeros(1000))  # 8,000 bytes: returned, not kept
    assert len(big) == 1000 and "big" not in cache.keys() and cache.bytes <= 3000
    with pytest.raises(ValueError, match=">= 0"):
        ImageCache(-1)


@pytest.mark.parametrize("matcher", ["exact", "words"])
def test_a_map_compares_the_same_within_a_small_budget(small_map: RouteMap, sunny2_features,
                                                       matcher: str) -> None:
    """Every image compared with budgets that keep all of them, a few of them, none: the same
    similarities, the budget never exceeded (the words matcher's word indexes share it)."""
    assert small_map.path is not None
    frames = sunny2_features[::10]
    ids = list(range(small_map.n_images))
    results = []
    for budget in (2**30, 200_000, 0):
        m = load_map(small_map.path, verify="lazy", matcher=matcher)
        m.image_cache.limit_bytes = budget
        peak = 0
        out = []
        for f in frames:
            for a in range(0, len(ids), 7):
                out.append(m.similarity(f, ids[a:a + 7]))
                peak = max(peak, m.image_cache.bytes)
        assert peak <= budget
        results.append(np.concatenate(out))
        if budget == 0:
            assert len(m.image_cache) == 0 and m.image_cache.made >= len(frames) * len(ids)
        if budget == 2**30:  # each image prepared once (words: its words and its index)
            assert m.image_cache.made == len(ids) * (1 if matcher == "exact" else 2)
    assert np.array_equal(results[0], results[1]) and np.array_equal(results[0], results[2])


def test_the_service_gives_its_maps_the_configured_budget(tmp_path: Path,
                                                          small_map: RouteMap) -> None:
    assert small_map.path is not None
    shutil.copy(small_map.path, tmp_path / "small.swmap")
    service = LocalizationService(Settings(maps_dir=tmp_path, session_store="memory",
                                           image_cache_mb=3))
    try:
        assert service.maps["small"].image_cache.limit_bytes == 3 * 2**20
    finally:
        service.close()
